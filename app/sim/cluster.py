"""Campaigns on a Ray cluster (``pip install '.[cluster]'``; ``midair simulate --ray [ADDRESS]``).

Each encounter is a pure function of (configuration, encounter), so it maps onto one Ray task:
the configuration goes to the object store once (``ray.put``), every task gets its reference,
and results come back in the order they finish (``ray.wait``), each written to the campaign's
``encounters.csv`` at once by the caller. A real-time encounter asks for
:data:`REALTIME_CPUS` CPUs, so that a node runs no more of them than it has cores to keep
their perception on time (the local pool's rule: half the cores, one encounter per two); a
faster-than-real-time object-free flight asks for one. A task whose worker is lost is run
again by Ray (``max_retries``); a driver stopped by Ctrl-C keeps what had finished (the
log) and ``--resume`` runs the rest.

Every node needs midair installed (the same version) in the Python that runs ``ray start``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from app.config import Config
from app.errors import UsageError
from app.sim.simulate import Encounter, EncounterResult

REALTIME_CPUS = 2  # per real-time encounter: perception thread + flight loop + vehicle
FAST_CPUS = 1  # per faster-than-real-time object-free flight (one busy thread)
MAX_RETRIES = 2  # a task whose worker died is run again this many times


def _ray() -> Any:
    try:
        import ray
    except ImportError:
        raise UsageError("--ray needs Ray: pip install 'midair[cluster]' (or: pip install ray)") from None
    return ray


def run_on_ray(cfg: Config, encounters: Sequence[Encounter],
               finished: Callable[[EncounterResult], None], fast_object_free: bool,
               address: str | None) -> None:
    """Run ``encounters`` as Ray tasks; call ``finished`` with each result as it arrives.
    ``address`` None or "local" starts a Ray runtime in this process's machine for the
    campaign; anything else (``auto``, ``HOST:6379``, ``ray://HOST:10001``) joins that
    cluster."""
    ray = _ray()
    started_here = False
    if not ray.is_initialized():
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False,
                                  "configure_logging": False}
        try:
            if address in (None, "local"):
                ray.init(**kwargs)
            else:
                ray.init(address=address, **kwargs)
        except ConnectionError as exc:
            raise UsageError(f"--ray {address}: no Ray cluster answered there ({exc}); start one "
                             "with `ray start --head` (README, 'Campaigns on a cluster')") from None
        started_here = True
    try:
        task = ray.remote(_task)
        cfg_ref = ray.put(cfg)  # once, not once per task

        def cpus(enc: Encounter) -> int:
            return FAST_CPUS if fast_object_free and not enc.with_object else REALTIME_CPUS

        pending = [task.options(num_cpus=cpus(enc), max_retries=MAX_RETRIES)
                   .remote(cfg_ref, enc, fast_object_free) for enc in encounters]
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            for ref in ready:
                finished(ray.get(ref))
    finally:
        if started_here:
            ray.shutdown()


def _task(cfg: Config, enc: Encounter, fast: bool) -> EncounterResult:
    """One encounter in a Ray worker (Ray resolves the top-level config reference)."""
    from app.sim.fast import run_one

    return run_one(cfg, enc, fast)
