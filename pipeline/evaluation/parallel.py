"""The experiments' replays side by side: every frame described first in threads, then replays in processes.

A replay is a deterministic function of (method, run, trial) and the filter settings: each one reseeds the
filter (`trial`), and frames are retrieved and encoded by deterministic ONNX passes. So the replays can run
in any order, anywhere, and give the figures `workers=1` gives (a test compares them). The filter itself is
single-threaded Python, numpy and numba, so processes rather than threads:

1. `prefetch_retrievals`: every frame of the runs is described and searched once in the parent, in
   `threads` threads with a single-threaded session of the bundle's detector graph each (onnxruntime
   releases the GIL), into the shared `CachedRetrieval` (with one worker too: no method's update times
   then include describing frames).
2. `replay_in_processes`: `workers` spawned processes (onnxruntime sessions must not cross a fork) each
   open the bundle again (checksums verified; the range table comes from the on-disk cache), take the
   parent's filter settings and the retrieval cache, and replay jobs as they come; each dies with the parent
   (`pipeline.workers.die_with_parent`). The sequence model's frame logits are computed in each worker
   when its replays need them.

Per-update times (`ms / update`) are measured with `workers` replays sharing the machine.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

_WORKER: dict = {}


def prefetch_retrievals(loc, data: Path, runs: list, retrieve, *, threads: int, progress: bool = True) -> None:
    """Describe and search every camera frame of `runs` not yet in `retrieve` (keys as the replays ask)."""
    from concurrent.futures import ThreadPoolExecutor

    from pipeline.progress import progress_bar
    from pipeline.runtime.describer import OnnxDescriber

    todo = list(dict.fromkeys(str(Path(data) / im) for run in runs for im in (run.image_ids or ()) if im))
    todo = [key for key in todo if key not in retrieve.cache]
    local = threading.local()

    def one(key: str):
        describer = getattr(local, "describer", None)
        if describer is None and threads == 1:
            describer = local.describer = loc.describer  # one thread: the Localizer's own session, all cores
        elif describer is None:
            models = Path(loc.root) / "models"
            describer = local.describer = OnnxDescriber(models / "describer.onnx", models / "describer.json",
                                                        threads=1)
        t0 = time.perf_counter()
        poses = loc.retrieved(key, describer=describer)
        return key, poses, time.perf_counter() - t0

    bar = progress_bar(total=len(todo), desc="describing frames", unit="frame", enabled=progress)
    with ThreadPoolExecutor(threads, thread_name_prefix="retrieval") as pool:
        for key, poses, seconds in pool.map(one, todo):
            retrieve.cache[key] = poses
            retrieve.seconds.append(seconds)
            bar.update(1)
    bar.close()


def _start_worker(parent_pid: int, root: str, filter_config: dict, retrieval: dict, base_seed: int, cache: dict,
                  data: str, runs: list, threshold_m: float, hold: int) -> None:
    from pipeline.workers import die_with_parent

    die_with_parent(parent_pid)  # first: a parent killed while the bundle loads must take this worker along
    from pipeline.config import FilterConfig
    from pipeline.evaluation.jobs import CachedRetrieval, PerImageCache
    from pipeline.runtime.localizer import Localizer

    loc = Localizer.from_bundle(Path(root), seed=base_seed, describer_threads=1)
    loc.filter_config = FilterConfig.model_validate(filter_config)  # the parent's: a study's variant included
    loc.base_seed, loc.retrieval = base_seed, retrieval
    retrieve = CachedRetrieval(loc)
    retrieve.cache.update(cache)
    loc.retrieved = retrieve
    if loc.sequence is not None:
        loc.sequence.encode = PerImageCache(loc.sequence.encode)
    _WORKER.update(loc=loc, data=Path(data), runs=runs, threshold_m=threshold_m, hold=hold)


def _replay(job: tuple[str, int, int]):
    from pipeline.evaluation.jobs import replay_job

    method, i, trial = job
    w = _WORKER
    return replay_job(w["loc"], w["data"], w["runs"][i], method, trial, w["threshold_m"], w["hold"])


def replay_in_processes(loc, data: Path, runs: list, jobs: list[tuple[str, int, int]], retrieve, *, workers: int,
                        threshold_m: float, hold: int, progress: bool = True) -> list:
    """The Replay of each (method, run index, trial) job, in job order, from `workers` processes."""
    import multiprocessing
    import os
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    from pipeline.progress import progress_bar

    args = (os.getpid(), str(loc.root), loc.filter_config.model_dump(mode="json"), dict(loc.retrieval),
            int(loc.base_seed), dict(retrieve.cache), str(data), runs, threshold_m, hold)
    bar = progress_bar(total=len(jobs), desc=f"experiments ({workers} processes)", unit="replay", enabled=progress)
    out = []
    try:
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                 initializer=_start_worker, initargs=args) as pool:
            for replay in pool.map(_replay, jobs):
                out.append(replay)
                bar.update(1)
    except BrokenProcessPool as exc:
        from pipeline.errors import SitelocError

        raise SitelocError(f"a replay process died ({exc}; its own error, if any, is printed above); rerun with "
                           f"--set evaluate.workers=1 to replay in this process") from None
    finally:
        bar.close()
    return out
