"""Place sets as other tools lay them out: two traversal folders, one folder with a BMP match matrix,
posed images, pair lists; and the refusals (a pickled ground truth, shapes, positions, rules)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from PIL import Image

from pipeline.errors import InputError
from pipeline.retrieval.place_set import natural_key, read_place_set


def images(folder, names):
    folder.mkdir(parents=True, exist_ok=True)
    for k, name in enumerate(names):
        Image.new("RGB", (8, 6), (k * 20 % 255, 40, 90)).save(folder / name)


def place_set(root, spec: dict):
    root.mkdir(parents=True, exist_ok=True)
    (root / "place_set.yaml").write_text(yaml.safe_dump(spec))
    return root


def test_two_traversals_aligned_in_natural_order(tmp_path):
    names = [f"{i}.jpg" for i in range(12)]  # 10.jpg after 9.jpg, not after 1.jpg
    images(tmp_path / "ref", names)
    images(tmp_path / "query", names)
    ps = read_place_set(place_set(tmp_path, {"database": "ref", "queries": "query", "positives": {"aligned": 2}}))
    assert [p.name for p in ps.database] == names and sorted(names, key=natural_key) == names
    i, j = np.indices((12, 12))
    np.testing.assert_array_equal(ps.positive, np.abs(i - j) <= 2)
    assert ps.name == tmp_path.name and ps.queries_with_positives == 12


@pytest.mark.parametrize("mode", ["1", "L"])
def test_one_folder_split_by_position_with_a_bmp_matrix_over_all_images(tmp_path, mode):
    # RTAB-Map's layout: 1.jpg..N.jpg and samples_GT.bmp beside them, loop closures below the diagonal only
    n = 10
    images(tmp_path, [f"{i}.jpg" for i in range(1, n + 1)])
    gt = np.zeros((n, n), np.uint8)
    for q, d in ((6, 0), (7, 1), (7, 2), (9, 4)):  # 0-based: image 7 sees image 1, ...
        gt[q, d] = 255
    Image.fromarray(gt).convert(mode).save(tmp_path / "samples_GT.bmp")
    ps = read_place_set(place_set(tmp_path, {"images": ".", "database": "1-5", "queries": "6-10",
                                             "positives": {"matrix": "samples_GT.bmp"}}))
    assert len(ps.database) == 5 and len(ps.queries) == 5  # the matrix is not taken for a view
    want = np.zeros((5, 5), bool)
    want[1, 0] = want[2, 1] = want[2, 2] = want[4, 4] = True
    np.testing.assert_array_equal(ps.positive, want)


def test_a_query_by_database_matrix_as_npy_and_csv(tmp_path):
    images(tmp_path / "db", ["a.png", "b.png", "c.png"])
    images(tmp_path / "q", ["x.png", "y.png"])
    m = np.array([[0, 1, 0], [1, 0, 1]])
    np.save(tmp_path / "gt.npy", m)
    np.savetxt(tmp_path / "gt.csv", m, delimiter=",", fmt="%d")
    for f in ("gt.npy", "gt.csv"):
        (tmp_path / "place_set.yaml").write_text(yaml.safe_dump({"database": "db", "queries": "q",
                                                                 "positives": {"matrix": f}}))
        np.testing.assert_array_equal(read_place_set(tmp_path).positive, m.astype(bool))


def test_posed_images_match_by_distance_and_angle(tmp_path):
    rng = np.random.default_rng(0)
    rows = ["image,x,y,theta_deg,role"]
    poses = []
    for k in range(20):
        x, y, th = rng.uniform(0, 6), rng.uniform(0, 6), rng.uniform(-180, 180)
        role = "database" if k < 12 else "query"
        rows.append(f"im/{k}.png,{x},{y},{th},{role}")
        poses.append((x, y, math.radians(th), role))
    images(tmp_path / "im", [f"{k}.png" for k in range(20)])
    (tmp_path / "poses.csv").write_text("\n".join(rows) + "\n")
    ps = read_place_set(place_set(tmp_path, {"poses": "poses.csv", "positives": {"distance_m": 2.5,
                                                                                   "angle_deg": 45}}))
    db = [p for p in poses if p[3] == "database"]
    qs = [p for p in poses if p[3] == "query"]
    for i, q in enumerate(qs):  # brute force
        for j, d in enumerate(db):
            dth = abs((q[2] - d[2] + math.pi) % (2 * math.pi) - math.pi)
            assert ps.positive[i, j] == (math.hypot(q[0] - d[0], q[1] - d[1]) <= 2.5 and dth <= math.radians(45))
    assert ps.database_poses.shape == (12, 3)


def test_pairs_by_name(tmp_path):
    images(tmp_path / "db", ["a.png", "b.png"])
    images(tmp_path / "q", ["x.png"])
    (tmp_path / "pairs.csv").write_text("query,database\nx.png,b.png\n")
    ps = read_place_set(place_set(tmp_path, {"database": "db", "queries": "q", "positives": {"pairs": "pairs.csv"}}))
    np.testing.assert_array_equal(ps.positive, [[False, True]])
    (tmp_path / "pairs.csv").write_text("query,database\nx.png,z.png\n")
    with pytest.raises(InputError, match="no database image 'z.png'") as err:
        read_place_set(tmp_path)
    assert "pairs.csv line 2" in str(err.value)


def refused(tmp_path, spec, *match):
    with pytest.raises(InputError) as err:
        read_place_set(place_set(tmp_path, spec))
    text = str(err.value)
    for m in match:
        assert m in text, text
    return text


def test_refusals_name_the_problem_and_the_fix(tmp_path):
    images(tmp_path / "db", ["a.png", "b.png", "c.png"])
    images(tmp_path / "q", ["x.png", "y.png"])
    # VPR-Bench's ground_truth_new.npy is an object array: reading it would unpickle
    np.save(tmp_path / "gt.npy", np.array([[0, [0, 1]], [1, [2]]], dtype=object), allow_pickle=True)
    refused(tmp_path, {"database": "db", "queries": "q", "positives": {"matrix": "gt.npy"}},
            "without unpickling", "aligned")
    np.save(tmp_path / "gt.npy", np.ones((3, 2)))
    refused(tmp_path, {"database": "db", "queries": "q", "positives": {"matrix": "gt.npy"}},
            "shape (3, 2), expected (2, 3)")
    refused(tmp_path, {"database": "db", "queries": "q", "positives": {"aligned": 1, "pairs": "p.csv"}},
            "exactly one of")
    refused(tmp_path, {"database": "db", "queries": "q", "positives": {"aligned": 1}, "extra": 1}, "extra")
    refused(tmp_path, {"database": "db", "queries": "nowhere", "positives": {"aligned": 1}}, "nowhere",
            "no such folder")
    refused(tmp_path, {"images": "db", "database": "1-2", "queries": "3-4", "positives": {"aligned": 1}},
            "3-4 is outside 1-3")
    refused(tmp_path, {"images": "db", "database": "1-2", "queries": "2-3", "positives": {"aligned": 1}},
            "both in the database and a query")
    np.save(tmp_path / "gt.npy", np.zeros((2, 3)))
    refused(tmp_path, {"database": "db", "queries": "q", "positives": {"matrix": "gt.npy"}}, "no query has a positive")
    (tmp_path / "poses.csv").write_text("image,x,y,theta_deg,role\ndb/a.png,0,0,0,database\ndb/b.png,0,0,0,dtabase\n")
    refused(tmp_path, {"poses": "poses.csv", "positives": {"distance_m": 1}}, "poses.csv line 3", "'dtabase'")


def test_an_ingested_site_is_a_posed_place_set(micro_site):
    import pyarrow.parquet as pq

    from pipeline.retrieval.place_set import load_places

    _, ingested, _ = micro_site
    ps = load_places(ingested, run_stride=3)
    images_table = pq.read_table(ingested / "images.parquet").to_pydict()
    train = [i for i, s in zip(images_table["image_id"], images_table["split"], strict=True) if s == "train"]
    assert [str(p.relative_to(ingested)) for p in ps.database] == train
    assert all(p.is_file() for p in ps.database + ps.queries)
    n_test = sum(s == "test" for s in images_table["split"])
    assert len(ps.queries) > n_test  # test stops, then every third frame of the query runs
    for i in range(len(ps.queries)):  # positives within 2 m and 30 deg, counted by hand
        for j in range(len(ps.database)):
            (qx, qy, qt), (dx, dy, dt) = ps.query_poses[i], ps.database_poses[j]
            dth = abs((qt - dt + math.pi) % (2 * math.pi) - math.pi)
            assert ps.positive[i, j] == (math.hypot(qx - dx, qy - dy) <= 2.0 and dth <= math.radians(30) + 1e-12)
