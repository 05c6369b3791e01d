"""One recording as a drive: its tf frames, its laser levelled, its odometry, its run and its capture stops.

The map, odom and base frames are found in tf (`--frame` names others; without a map frame connected to the
base the drive has no reference: a run of estimates without ground truth). An upside-down laser's scans are
mirrored to an upright one's, a tilted one is refused. The run is a step per scan with the odometry (odom ->
base, from /tf, else /odom) and the reference interpolated at the scan's stamp, and the camera frame nearest
in time; the stops are the camera frames of turns in place (`pipeline.rosbag.stops`). `recording_notes` says
how the recording was read (odometry source, reference, laser), for the report and the CLI.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.errors import InputError, Problem
from pipeline.rosbag.messages import yaw_quat
from pipeline.rosbag.read import Recording
from pipeline.rosbag.scans import Grid, mirror
from pipeline.rosbag.stops import stops_every, turning_stops
from pipeline.runtime.motion import compose2d, inverse2d, wrap_angle

#: A laser whose scan plane leans further than this from the floor's is refused.
LEVEL_TOLERANCE_DEG = 10.0
#: /odom and tf's odom -> base disagreeing by more than this (motion since the start) is reported.
ODOM_DISAGREE_M, ODOM_DISAGREE_DEG = 0.05, 2.0


@dataclass
class BagOptions:
    roles: dict[str, str] = field(default_factory=dict)  # role -> topic
    offsets: dict[str, float] = field(default_factory=dict)  # role -> seconds added to its stamps
    frames: dict[str, str] = field(default_factory=dict)  # map / odom / base -> frame name
    stops: str = "turns"  # turns | every
    stops_every_m: float = 2.0
    stops_from: list[str] = field(default_factory=list)  # recordings to take stops from (empty: all)
    stop_radius_m: float = 0.05
    view_tolerance_deg: float | None = None  # default: ingest.heading_tolerance_deg (turns), 15 (every)
    sync_tolerance_s: float = 0.05
    tf_max_gap_s: float = 0.5
    kidnap_jump_m: float = 1.0
    kidnap_jump_deg: float = 45.0
    scan_stride: int = 1
    name: str | None = None


@dataclass
class Drive:
    rec: Recording
    stops: list = field(default_factory=list)
    incomplete: list = field(default_factory=list)
    run: dict | None = None
    report: dict = field(default_factory=dict)


def _base_frame(rec: Recording, opts: BagOptions, odom: str) -> str:
    """The robot's base: --frame base=..., else /odom's child frame, else the one frame odom moves in tf,
    else base_link or base_footprint, whichever tf has."""
    if "base" in opts.frames:
        return opts.frames["base"].lstrip("/")
    if rec.base_frame:
        return rec.base_frame
    moving = [c for c, e in rec.tf.edges.items() if e.parent == odom and not e.static]
    if len(moving) == 1:
        return moving[0]
    known = rec.tf.frames()
    return next((f for f in ("base_link", "base_footprint") if f in known), "base_link")


def _frames(rec: Recording, opts: BagOptions) -> tuple[str | None, str, str]:
    """(map or None, odom, base) frames. Without a map frame connected to the base the recording has no
    reference (no localization was recorded): its runs have estimates but no ground truth."""
    m = opts.frames.get("map", "map").lstrip("/")
    odom = opts.frames.get("odom", rec.odom_frame or "odom").lstrip("/")
    base = _base_frame(rec, opts, odom)
    known = rec.tf.frames()
    fix = "record /tf with odom -> base_link (or /odom); --frame odom=NAME --frame base=NAME name others"
    for role, f in (("base", base), ("odom", odom)):
        if f not in known:
            raise InputError(f"{rec.path}: no frame '{f}' in tf", [Problem(
                f"{rec.path} /tf", f"the {role} frame '{f}' never appears, so there is no odometry (frames: "
                f"{sorted(known)})", fix=fix)])
    if rec.tf.path(odom, base) is None:
        raise InputError(f"{rec.path}: tf has no {odom} -> {base}", [Problem(
            f"{rec.path} /tf", f"'{odom}' and '{base}' are not connected (tree: {_tree(rec)})", fix=fix)])
    if m not in known or rec.tf.path(m, base) is None:
        if "map" in opts.frames:
            raise InputError(f"{rec.path}: no frame '{m}' connected to '{base}' in tf", [Problem(
                f"{rec.path} /tf", f"--frame map={m}: not connected to '{base}' (tree: {_tree(rec)})",
                fix="name the reference frame that tf connects to the base, or leave --frame map out")])
        return None, odom, base
    return m, odom, base


def _tree(rec: Recording) -> str:
    return ", ".join(f"{e.parent} -> {c}" for c, e in sorted(rec.tf.edges.items()))


def _mount(rec: Recording, base: str, frame: str | None, what: str):
    """base_from_sensor at the first stamp; the sensor must hang off the base in tf."""
    if frame is None:
        return None
    if rec.tf.path(base, frame) is None:
        raise InputError(f"{rec.path}: the {what} is not in the tf tree", [Problem(
            f"{rec.path} /tf_static", f"no transform between '{base}' and the {what} frame '{frame}'",
            fix=f"record /tf_static with the {what}'s mount ({base} -> {frame})")])
    return rec.tf.lookup(base, frame, [0.0])


def _gaps(rec: Recording, m: str, base: str, stamps: np.ndarray) -> list[dict]:
    out = []
    up, down = rec.tf.path(m, base)
    for child in up[:-1] + down[:-1]:
        for a, b in rec.tf.gaps(child):
            inside = int(np.sum((stamps > a) & (stamps < b)))
            out.append({"edge": f"{rec.tf.edges[child].parent} -> {child}", "from_s": round(a - start_stamp(rec), 3),
                        "to_s": round(b - start_stamp(rec), 3), "gap_s": round(b - a, 3), "stamps_inside": inside})
    return out


def stream_gaps(rec: Recording, factor: float = 2.5, min_gap: float = 1.0) -> list[dict]:
    """Silences of the laser (the runs' clock): intervals longer than `factor` typical periods and `min_gap`
    seconds, where a sensor or the recorder stalled or the clock jumped forward. (The camera is not
    checked: a capture camera may fire only at the views.)"""
    stamps = rec.scan_stamps
    if stamps is None or len(stamps) < 3:
        return []
    d = np.diff(stamps)
    period = float(np.median(d))
    limit = max(factor * period, min_gap)
    return [{"topic": rec.topics.get("scan", "scan"), "from_s": round(float(stamps[i]) - start_stamp(rec), 3),
             "to_s": round(float(stamps[i + 1]) - start_stamp(rec), 3), "gap_s": round(float(d[i]), 3),
             "typical_period_s": round(period, 3)} for i in np.nonzero(d > limit)[0]]


def start_stamp(rec: Recording) -> float:
    firsts = [f[0] for f in rec.frames[:1]] + ([float(rec.scan_stamps[0])] if rec.scan_stamps is not None else [])
    return min(firsts) if firsts else 0.0


def level_laser(rec: Recording, base: str) -> None:
    """Bring an upside-down laser's scans to an upright one's (`scans.mirror`); refuse a tilted laser.
    Once per recording: the geometry in `rec.laser` says whether it was done."""
    if rec.laser is None or "mirrored" in rec.laser:
        return
    mount = _mount(rec, base, rec.laser_frame, "laser")
    up = float(mount.rot.as_matrix()[0][2, 2])  # the laser's z axis, seen from the base's
    if abs(up) < math.cos(math.radians(LEVEL_TOLERANCE_DEG)):
        raise InputError(f"{rec.path}: the laser is tilted", [Problem(
            f"{rec.path} /tf_static {base} -> {rec.laser_frame}", f"the scan plane is tilted "
            f"{math.degrees(math.acos(min(abs(up), 1.0))):.1f} deg from level (at most {LEVEL_TOLERANCE_DEG} deg)",
            fix="a 2-D filter needs a level scan: check the mount in tf_static (a URDF error?) or flatten the scan "
                "(pointcloud_to_laserscan)")])
    rec.laser["mirrored"] = up < 0
    if up < 0:
        grid = Grid(rec.laser["angle_min"], rec.laser["angle_increment"], rec.laser["beams"])
        rec.ranges, flipped = mirror(rec.ranges, grid)
        rec.laser["angle_min"] = flipped.angle_min


def _odometry_report(rec: Recording, odom_f: str, base: str, stamps: np.ndarray) -> dict:
    """Which odometry the runs use (tf's odom -> base, else /odom) and, with both, how far they disagree."""
    topic = rec.topics.get("odom")
    if rec.odometry_source != "tf" or not rec.odom_msgs or len(stamps) == 0:
        return {"source": rec.odometry_source, "topic": topic}
    from pipeline.rosbag.transforms import TfBuffer

    other = TfBuffer(rec.tf.max_gap, rec.tf.tolerance)
    other.edges["base"] = rec.odom_msgs
    a, b = rec.tf.lookup(odom_f, base, stamps), other.lookup("odom", "base", stamps)
    both = a.valid & b.valid
    if not both.any():
        return {"source": "tf", "topic": topic}
    pa, pb = a.floor_pose(0)[both], b.floor_pose(0)[both]
    # Frames may start apart (each its own origin): compare the motion since the first common stamp.
    da, db = compose2d(inverse2d(pa[:1]), pa), compose2d(inverse2d(pb[:1]), pb)
    dist = np.hypot(*(da[:, :2] - db[:, :2]).T)
    turn = np.degrees(np.abs(wrap_angle(da[:, 2] - db[:, 2])))
    return {"source": "tf", "topic": topic, "topic_disagrees_m_max": round(float(dist.max()), 4),
            "topic_disagrees_deg_max": round(float(turn.max()), 3),
            "disagrees": bool(dist.max() > ODOM_DISAGREE_M or turn.max() > ODOM_DISAGREE_DEG)}


def extract_drive(rec: Recording, site_offsets, opts: BagOptions, tol_deg: float, use_stops: bool) -> Drive:
    m, odom_f, base = _frames(rec, opts)
    level_laser(rec, base)
    drive = Drive(rec, report={"reference": m is not None, "frames": {"map": m, "odom": odom_f, "base": base}})
    cam_mount = _mount(rec, base, rec.camera_frame, "camera")
    dropped = {"duplicate_stamps": len(rec.dropped)}
    if rec.frames and m is None:
        if rec.ranges is None:  # a camera-only recording is a capture: its stops need where each frame was taken
            raise InputError(f"{rec.path}: no reference in tf", [Problem(
                f"{rec.path} /tf", f"camera frames need a pose, and no frame 'map' connects to '{base}' "
                f"(tree: {_tree(rec)})", fix="record the localization's map -> odom (or motion capture) with the "
                "camera; --frame map=NAME names another reference frame")])
        dropped["frames_without_pose"] = len(rec.frames)
    elif rec.frames:
        fs = np.array([f[0] for f in rec.frames])
        map_from_base = rec.tf.lookup(m, base, fs)
        ok = map_from_base.valid
        dropped["frames_without_pose"] = int((~ok).sum())
        map_from_cam = map_from_base * cam_mount if cam_mount is not None else map_from_base
        cam = map_from_cam.floor_pose(2)
        keep = np.nonzero(ok)[0]
        if use_stops and len(keep):
            tol = math.radians(tol_deg)
            if opts.stops == "every":
                st, inc = stops_every(fs[keep], map_from_base.xyz[keep, :2], cam[keep], site_offsets,
                                      spacing=opts.stops_every_m, tolerance=tol)
            else:
                st, inc = turning_stops(fs[keep], map_from_base.xyz[keep, :2], cam[keep], site_offsets,
                                        radius=opts.stop_radius_m, tolerance=tol)
            for s in st:
                s.frames = [int(keep[f]) for f in s.frames]
            drive.stops, drive.incomplete = st, inc
        drive.report["cam_poses"] = cam
    if rec.ranges is not None:
        idx = np.arange(0, len(rec.scan_stamps), max(1, opts.scan_stride))
        t = rec.scan_stamps[idx]
        odom = rec.tf.lookup(odom_f, base, t)
        ref = rec.tf.lookup(m, base, t) if m is not None else None
        ok = odom.valid
        drive.report["odometry"] = _odometry_report(rec, odom_f, base, t)
        if ref is None:
            ref = odom.__class__(odom.rot, np.full_like(odom.xyz, np.nan), np.zeros(len(t), bool))
        dropped["scans_without_odometry"] = int((~ok).sum())
        if m is not None:
            dropped["scans_without_reference"] = int((ok & ~ref.valid).sum())
        idx, t = idx[ok], t[ok]
        odom_p, ref_p = odom.floor_pose(0)[ok], np.where(ref.valid[ok, None], ref.floor_pose(0)[ok], np.nan)
        image = [None] * len(t)
        if rec.frames and len(t):
            fs = np.array([f[0] for f in rec.frames])
            near = np.clip(np.searchsorted(t, fs), 1, len(t) - 1) if len(t) > 1 else np.zeros(len(fs), int)
            near = np.where(np.abs(t[near - 1] - fs) <= np.abs(t[near] - fs), near - 1, near) if len(t) > 1 else near
            dt = np.abs(t[near] - fs)
            best: dict[int, int] = {}
            for fi in np.argsort(dt, kind="stable"):
                if dt[fi] <= opts.sync_tolerance_s and int(near[fi]) not in best:
                    best[int(near[fi])] = int(fi)
            for step, fi in best.items():
                image[step] = fi
            dropped["frames_without_scan"] = len(fs) - len(best)
            dropped["sync_tolerance_s"] = opts.sync_tolerance_s
        drive.run = {"t": t - t[0] if len(t) else t, "t0": float(t[0]) if len(t) else 0.0, "odom": odom_p,
                     "gt": ref_p, "ranges": rec.ranges if len(idx) == len(rec.ranges) else rec.ranges[idx],
                     "image": image, "kidnapped": _kidnapped(odom_p, ref_p, opts)}
        dropped["tf_gaps"] = _gaps(rec, m or odom_f, base, np.r_[t, [f[0] for f in rec.frames]])
        dropped["resampled_scans"] = rec.resampled_scans
    dropped["stream_gaps"] = stream_gaps(rec)
    drive.report["dropped"] = dropped
    return drive


def kept_frames(d: Drive) -> set[int]:
    """Positions in `d.rec.frames` of the frames the capture directory keeps: stop views and run frames."""
    out = {f for s in d.stops for f in s.frames}
    if d.run is not None:
        out |= {f for f in d.run["image"] if f is not None}
    return out


def _kidnapped(odom: np.ndarray, ref: np.ndarray, opts: BagOptions) -> list[bool]:
    """Step k is kidnapped when the reference moved unlike the odometry since step k-1."""
    out = [False] * len(odom)
    if len(odom) < 2:
        return out
    d_odom = compose2d(inverse2d(odom[:-1]), odom[1:])
    d_ref = compose2d(inverse2d(ref[:-1]), ref[1:])
    jump = np.hypot(*(d_ref[:, :2] - d_odom[:, :2]).T)
    turn = np.abs(wrap_angle(d_ref[:, 2] - d_odom[:, 2]))
    flag = (jump > opts.kidnap_jump_m) | (turn > math.radians(opts.kidnap_jump_deg))
    for k in np.nonzero(flag)[0]:
        out[k + 1] = True
    return out


def site_of(recs: list[Recording], drives: list[Drive], name: str, opts: BagOptions):
    """site.yaml from the recordings: the camera of those with one (none: a laser-only site), the laser of the
    first with scans, the mounts from tf_static."""
    from pipeline.io.site import Extrinsic, Extrinsics, Laser, Site

    with_cam = [r for r in recs if r.intrinsics is not None]
    camera, laser, ext = None, Laser(), {}
    if with_cam:
        camera = with_cam[0].intrinsics
        for r in with_cam[1:]:
            if r.intrinsics != camera:
                raise InputError("recordings disagree on the camera", [Problem(
                    f"{r.path} {r.topics['camera_info']}", f"intrinsics {r.intrinsics} differ from {camera} "
                    f"({with_cam[0].path})", fix="ingest recordings of one calibrated camera together")])
    with_laser = [r for r in recs if r.laser is not None]
    for r in with_laser[1:]:
        if r.laser["beams"] != with_laser[0].laser["beams"]:
            raise InputError("recordings disagree on the laser", [Problem(
                f"{r.path} {r.topics['scan']}", f"{r.laser['beams']} beams, {with_laser[0].path} has "
                f"{with_laser[0].laser['beams']}", fix="ingest recordings of one laser configuration together")])
    if with_laser:
        laser, ext["base_from_laser"] = laser_of(with_laser[0], opts)
    if with_cam:
        r = with_cam[0]
        _, _, base = _frames(r, opts)
        cm = _mount(r, base, r.camera_frame, "camera")
        ext["base_from_camera"] = Extrinsic(xyz=tuple(np.round(cm.xyz[0], 6)),
                                            quat_xyzw=tuple(np.round(cm.rot.as_quat()[0], 9)))
    return Site(name=name, camera=camera, laser=laser, extrinsics=Extrinsics(**ext))


def laser_of(r: Recording, opts: BagOptions):
    """site.yaml's laser (the recording's beam grid, 2-D mount) and its 3-D extrinsic, from a recording. An
    upside-down laser's scans were mirrored (`level_laser`): its extrinsic is the upright mount at its yaw."""
    from pipeline.io.site import Extrinsic, Laser, LaserMount

    _, _, base = _frames(r, opts)
    level_laser(r, base)
    g = r.laser
    mount = _mount(r, base, r.laser_frame, "laser")
    mx, my, myaw = mount.floor_pose(0)[0]
    laser = Laser(angle_min_deg=round(math.degrees(g["angle_min"]), 4),
                  angle_max_deg=round(math.degrees(g["angle_min"] + (g["beams"] - 1) * g["angle_increment"]), 4),
                  beams=g["beams"], range_max=g["range_max"],
                  mount=LaserMount(x=round(mx, 6), y=round(my, 6), yaw_deg=round(math.degrees(myaw), 6)))
    quat = yaw_quat(myaw) if g.get("mirrored") else mount.rot.as_quat()[0]
    return laser, Extrinsic(xyz=tuple(np.round(mount.xyz[0], 6)), quat_xyzw=tuple(np.round(quat, 9)))


def map_of(recs: list[Recording], map_yaml: Path | None):
    from pipeline.io.map_yaml import read_map

    if map_yaml is not None:
        return read_map(map_yaml)
    for r in recs:
        if r.grid is not None:
            return r.grid
    raise InputError("no map", [Problem(str(recs[0].path), "no nav_msgs/OccupancyGrid topic in any recording",
                                        fix="record /map (map_server publishes it) or pass --map map.yaml")])


def recording_notes(d: Drive) -> dict:
    """What a user should know about how a recording was read: odometry source, reference, laser."""
    laser = d.rec.laser or {}
    return {"odometry": d.report.get("odometry"), "reference": d.report.get("reference"),
            "laser": {"frame": d.rec.laser_frame, "mirrored": bool(laser.get("mirrored")),
                      "resampled_scans": d.rec.resampled_scans} if laser else None}


def notes_text(r: dict) -> list[str]:
    """`recording_notes` as sentences (bag_report.md, the CLI)."""
    out = []
    odo = r.get("odometry") or {}
    if odo.get("source") == "tf":
        out.append("odometry from /tf (odom -> base)" + (
            f"; {odo['topic']} disagrees by up to {odo['topic_disagrees_m_max']} m / "
            f"{odo['topic_disagrees_deg_max']} deg and is not used" if odo.get("disagrees") else
            f"; {odo['topic']} agrees" if odo.get("topic") and "topic_disagrees_m_max" in odo else ""))
    elif odo.get("source") == "topic":
        out.append(f"odometry from {odo.get('topic')} (nav_msgs/Odometry; /tf has no odom -> base)")
    if r.get("reference") is False:
        out.append("no reference (no map frame in tf): estimates without error metrics")
    laser = r.get("laser") or {}
    if laser.get("mirrored"):
        out.append(f"the laser '{laser['frame']}' is mounted upside down: its scans are mirrored")
    if laser.get("resampled_scans"):
        out.append(f"{laser['resampled_scans']} scans had another beam count or sweep and were resampled onto the "
                   "first scan's beams")
    return out
