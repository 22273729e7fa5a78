"""A batch: every part of a manifest inspected, recorded in the results database, summed up.

Parts run on local worker processes (one per core by default) or, with a
scheduler address, on a Dask distributed cluster; either way each part is
:func:`partinspect.production.worker.inspect_part`, and the results flow
back to this process, the database's one writer, which records each part
in its own transaction as soon as it is done.

The batch's exit code, from its parts' (DESIGN.md's codes per part): 2 when
any part could not be run (a bad manifest line included), else 1 when any
part fails, else 3 when any is inconclusive, else 0. A part that cannot be
run is the most urgent: its result is unknown, and it may hide a fail.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass, field
from pathlib import Path

from partinspect import __version__
from partinspect.atomic import prepare_output_dir
from partinspect.errors import InputError
from partinspect.progress import quiet

EXIT_PASS, EXIT_FAIL, EXIT_ERROR, EXIT_INCONCLUSIVE = 0, 1, 2, 3


@dataclass
class BatchResult:
    """What a batch did.

    Attributes
    ----------
    records : list of dict
        The ``parts`` rows written by this run, in completion order.
    skipped : dict of str to int
        Serials already done in the batch being resumed, with their exit codes.
    problems : list of str
        Manifest lines left out, one line each.
    url : str
        The results database.
    batch_id : int
    """

    records: list = field(default_factory=list)
    skipped: dict = field(default_factory=dict)
    problems: list = field(default_factory=list)
    url: str = ""
    batch_id: int = 0
    spc_page: Path | None = None

    @property
    def exit_code(self):
        codes = [r["exit_code"] for r in self.records] + list(self.skipped.values())
        return batch_exit_code(codes, len(self.problems))

    def summary_line(self):
        n = {k: sum(r["verdict"] == k for r in self.records) for k in ("pass", "fail", "inconclusive")}
        failed = sum(r["status"] == "failed" for r in self.records)
        asked = [r["rig_refined"] for r in self.records if r.get("rig_refined") is not None]
        return (f"BATCH {('PASS', 'FAIL', 'ERROR', 'INCONCLUSIVE')[self.exit_code]}: {len(self.records)} part(s) "
                f"inspected: {n['pass']} pass, {n['fail']} fail, {n['inconclusive']} inconclusive, {failed} could not "
                f"be run" + (f"; {len(self.skipped)} already done" if self.skipped else "")
                + (f"; {len(self.problems)} manifest line(s) left out" if self.problems else "")
                + (f"; rig refined from the part in {sum(asked)} of {len(asked)}" if asked else "")
                + f"; database: {self.url}" + (f"; SPC: {self.spc_page}" if self.spc_page else ""))


def batch_exit_code(codes, problems=0):
    """The batch's exit code from its parts' codes (module docstring's rule).

    >>> batch_exit_code([0, 3, 1]), batch_exit_code([0, 3]), batch_exit_code([0, 0], problems=1)
    (1, 3, 2)
    """
    codes = set(codes)
    if problems or EXIT_ERROR in codes:
        return EXIT_ERROR
    for code in (EXIT_FAIL, EXIT_INCONCLUSIVE):
        if code in codes:
            return code
    return EXIT_PASS


def run_batch(manifest, out, *, db=None, step=None, resume=False, workers=None, scheduler=None, progress=quiet,
              on_problem=None, spc=True, subgroup_size=None, refine_rig=False):
    """Inspect every part of ``manifest`` into ``out/SERIAL/`` and record them in the results database.

    Parameters
    ----------
    manifest : str or Path
        CSV, YAML or folder layout (:func:`partinspect.production.manifest.read_manifest`).
    out : str or Path
        The batch's output folder; the SQLite database and the SPC page go here too.
    db : str, optional
        Database URL or SQLite file; default ``out/results.sqlite``.
    step : str or Path, optional
        The STEP file of a folder layout.
    resume : bool
        Continue the latest batch into ``out``: parts recorded as done are
        not inspected again (parts that could not be run are tried again).
    workers : int, optional
        Local worker processes; default one per core.
    scheduler : str, optional
        ``tcp://HOST:PORT`` of a Dask scheduler: the parts run on its
        workers, which must see the same paths (a shared file system).
    progress : callable
        ``progress(message)`` as parts complete.
    on_problem : callable, optional
        ``on_problem(line)`` for each bad manifest line, as soon as it is
        read, and each part that could not be run, as soon as it is back.
    spc : bool
        Write ``out/spc.html`` over the batch's parts when done.
    subgroup_size : int, optional
        The SPC page's subgroups (:func:`partinspect.production.spc_report.with_subgroups`).
    refine_rig : bool
        Every part's rig refined from its own circles, as a single run's
        (:func:`partinspect.production.worker.inspect_part`); each part's
        ``rig_refined`` row and the summary line say where it was.

    Returns
    -------
    BatchResult
    """
    from partinspect.production.database import database_url, open_database, record_part, shown_url, start_batch
    from partinspect.production.manifest import read_manifest
    from partinspect.production.spc_report import check_subgroup_size

    check_subgroup_size(subgroup_size)
    jobs, problems = read_manifest(manifest, step)
    for line in problems:
        (on_problem or progress)(line)
    if not jobs:
        raise InputError(manifest, f"no part to inspect: every line has a problem ({len(problems)})")
    if workers is not None and workers < 1:
        raise InputError(None, f"--workers {workers}: at least one worker")
    out = prepare_output_dir(out)
    url = database_url(db, out)
    engine = open_database(url)
    batch_id, done = start_batch(engine, str(out.resolve()), str(Path(manifest).resolve()), __version__,
                                 resume=resume)
    result = BatchResult(problems=problems, url=shown_url(url), batch_id=batch_id)
    # A resumed batch's code covers its parts done before, not only this run's.
    result.skipped = {j.serial: done[j.serial] for j in jobs if j.serial in done}
    todo = [j for j in jobs if j.serial not in done]
    progress(f"{len(todo)} part(s) to inspect" + (f", {len(result.skipped)} already done" if result.skipped else "")
             + (f" on the Dask cluster at {scheduler}" if scheduler else ""))
    run = _run_on_dask if scheduler else _run_locally
    for i, rec in enumerate(run(todo, out.resolve(), scheduler or workers, refine_rig), 1):
        record_part(engine, batch_id, rec["part"], rec["characteristics"])
        p = rec["part"]
        result.records.append(p)
        progress(f"{p['serial']}: {p['verdict'] or 'could not be run'} ({i} of {len(todo)}, {p['seconds']:.1f} s)")
        if p["status"] == "failed":
            (on_problem or progress)(f"{p['serial']}: could not be run: {p['error']}")
    if spc:
        from partinspect.production.spc_report import write_spc_page

        result.spc_page = write_spc_page(engine, out, batch_id=batch_id, title=f"SPC of batch {out.name}",
                                         subgroup_size=subgroup_size)
    engine.dispose()
    return result


#: Modules the forkserver imports once, so that every worker forked from it
#: starts with them: the pipeline's stages import theirs on first use.
PRELOAD = ("partinspect.pipeline", "partinspect.production.worker", "partinspect.adaptive",
           "partinspect.vision.stereo", "partinspect.vision.epipolar_drift", "partinspect.cad.model",
           "partinspect.cad.registration", "partinspect.cad.visibility", "partinspect.tolerances.evaluate",
           "partinspect.tolerances.loading", "partinspect.reports.writer")
#: Thread pools sized by the environment when a library loads (OpenBLAS, OpenMP, MKL).
THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def _run_locally(jobs, out, workers, refine_rig=False):
    """Each finished part's record, from a pool of worker processes that live through the batch.

    The workers share the CPUs: each computes on ``CPUs // workers`` of
    them (at least one), its libraries' thread pools sized to that and, with
    fewer than two, no forked child of its own (:mod:`partinspect.vision.forked`).
    Two workers on two CPUs each running two BLAS and OpenCV threads, or
    forking a second process whenever the load average lags behind, would
    compute four-to-a-pair and take turns; Dask's nanny limits its
    workers' threads the same way.
    """
    from partinspect.production.worker import inspect_part, share_cpus

    cpus = os.cpu_count() or 1
    workers = min(workers or cpus, max(len(jobs), 1))
    if workers == 1:
        # One worker: this process is it (warm across parts all the same), with every CPU.
        for job in jobs:
            yield inspect_part(job, out, refine_rig)
        return
    import concurrent.futures as cf
    import multiprocessing

    threads = max(1, cpus // workers)
    # forkserver: a clean worker, not a copy of this process's database
    # connection; the package is imported once in the server, then forked.
    # The server, started by a process's first batch, keeps the thread
    # variables it started with.
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(list(PRELOAD))
    with _environment({v: str(threads) for v in THREAD_VARIABLES}), \
            cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=share_cpus,
                                   initargs=(threads,)) as pool:
        futures = {pool.submit(inspect_part, job, out, refine_rig): job for job in jobs}
        try:
            for f in cf.as_completed(futures):
                try:
                    yield f.result()
                except cf.process.BrokenProcessPool as exc:
                    # A worker died (killed, out of memory): this part and
                    # those queued behind it are recorded as not run.
                    yield _lost(futures[f], exc)
        except BaseException:
            for f in futures:
                f.cancel()
            raise


@contextlib.contextmanager
def _environment(values):
    """``os.environ`` with ``values`` set (those the user set are kept), restored on exit."""
    old = {k: os.environ.get(k) for k in values}
    os.environ.update({k: v for k, v in values.items() if old[k] is None})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)


def _run_on_dask(jobs, out, scheduler, refine_rig=False):
    """Each finished part's record, from the workers of the Dask cluster at ``scheduler``."""
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise InputError(None, "--scheduler needs Dask distributed (pip install distributed)") from None
    from partinspect.production.worker import inspect_part

    try:
        client = Client(scheduler, timeout="20s")
    except (OSError, TimeoutError) as exc:
        raise InputError(None, f"--scheduler {scheduler}: cannot reach the Dask scheduler ({exc})") from None
    try:
        # pure=False: the same part inspected twice is two runs, not one cached result.
        futures = client.map(inspect_part, jobs, out=out, refine_rig=refine_rig, pure=False)
        job_of = {f.key: job for f, job in zip(futures, jobs)}
        for f in as_completed(futures):
            try:
                yield f.result()
            except Exception as exc:  # the worker died (KilledWorker) or the task failed outside the pipeline
                yield _lost(job_of[f.key], exc)
    finally:
        client.close()


def _lost(job, exc):
    """The record of a part whose worker was lost before it answered."""
    from datetime import datetime, timezone

    return {"part": {"serial": job.serial, "step_file": str(job.step), "images": str(job.images),
                     "spec_file": None if job.spec is None else str(job.spec),
                     "measured_at": job.time or datetime.now(timezone.utc).replace(tzinfo=None, microsecond=0),
                     "software_version": __version__, "status": "failed", "exit_code": EXIT_ERROR, "verdict": None,
                     "error": f"its worker was lost: {type(exc).__name__}: {' '.join(str(exc).split())}",
                     "seconds": 0.0, "subgroup": job.subgroup, "rig_refined": None},
            "characteristics": []}

