"""Ray for the stages that scale with images (`--engine ray`): chunks of work on a pool of Ray actors.

A stage splits its images into resumable chunks as it does locally; the chunks still to do become a Ray
Dataset of chunk numbers, and `map_batches` hands them one at a time to an actor pool. Each actor is built
once (it loads its ONNX graphs) and writes its chunk's output files itself, under a temporary name renamed
when complete, so a chunk is done exactly when its files exist: a task lost with its worker is retried
by Ray Data (on a new actor), and an interrupted run resumes from the finished chunks like the local one.
The driver then merges the chunk files as the local path does, so both write the same tables.
On a cluster the stage's output directory must be on storage every node sees.

Ray is an optional extra (`pip install 'siteloc[ray]'`); docs/scaling.md.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

from pipeline.errors import SitelocError


def connect(address: str | None, *, num_cpus: int | None = None):
    """ray, initialised: a local instance (`address` None; `num_cpus` caps it) or the cluster at `address`
    ("auto", or host:port of its head). A missing extra or an unreachable address is a SitelocError that
    says what to do."""
    try:
        import ray
    except ImportError:
        raise SitelocError("--engine ray needs Ray: pip install 'siteloc[ray]' (ray[data])") from None
    if ray.is_initialized():
        return ray
    if address not in (None, "auto"):
        _reachable(address)  # Ray itself retries an unreachable address for minutes, logging as it goes
    try:
        if address is None:
            ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False, configure_logging=False)
        else:
            ray.init(address=address, log_to_driver=False, configure_logging=False)
    except (ConnectionError, ValueError, RuntimeError, TimeoutError) as exc:
        first = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else type(exc).__name__
        raise SitelocError(f"--ray-address {address}: cannot connect to a Ray cluster there ({first}); start one "
                           f"with `ray start --head` and pass its address (host:6379), or leave --ray-address out "
                           f"for a local Ray") from None
    return ray


def run_chunks(ray, chunks: Iterable[dict], actor: type, actor_kwargs: dict, *, workers: int,
               on_done: Callable[[int, int], None]) -> None:
    """Give each chunk (a dict with its number under "chunk" and what the actor needs) to
    `actor(**actor_kwargs)(batch)` on a pool of `workers` actors (one CPU each); `on_done(chunk, items)`
    after each, from what the actor returned ({"chunk": [k], "items": [n]})."""
    chunks = list(chunks)
    if not chunks:
        return
    import ray.data

    ctx = ray.data.DataContext.get_current()
    ctx.enable_progress_bars = False  # the stage shows its own
    ctx.print_on_execution_start = False
    ds = ray.data.from_items(chunks, override_num_blocks=len(chunks))
    done = ds.map_batches(actor, fn_constructor_kwargs=actor_kwargs, batch_size=1, concurrency=workers, num_cpus=1,
                          zero_copy_batch=True)
    for row in done.iter_rows():
        on_done(int(row["chunk"]), int(row["items"]))


def run_on_ray(ray_address: str | None, chunks: list[dict], actor: type, actor_kwargs: dict, *,
               on_done: Callable[[int, int], None]) -> None:
    """`run_chunks` on the cluster at `ray_address` (None: a local Ray on the usable cores), one actor per CPU
    (at most one per chunk)."""
    from pipeline.machine import usable_core_count

    ray = connect(ray_address, num_cpus=None if ray_address else usable_core_count())
    workers = max(1, min(len(chunks), int(ray.available_resources().get("CPU", 1))))
    run_chunks(ray, chunks, actor, actor_kwargs, workers=workers, on_done=on_done)


def _reachable(address: str, timeout_s: float = 5.0) -> None:
    """Refuse an address whose port does not answer (ray://host:port or host:port)."""
    import socket

    hostport = address.split("://", 1)[-1]
    host, _, port = hostport.rpartition(":")
    fix = "start a cluster with `ray start --head` and pass its address (host:6379), or leave --ray-address out"
    if not host or not port.isdigit():
        raise SitelocError(f"--ray-address {address}: not host:port; {fix}")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise SitelocError(f"--ray-address {address}: nothing answers there ({exc.strerror or exc}); {fix}") from None
