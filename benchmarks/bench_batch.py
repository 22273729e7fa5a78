"""Throughput of `inspect batch` against a shell loop of `inspect` processes, on the same rendered parts.

Renders N plates (cached in --dir), the 12 mm hole circle-4 drifting in
diameter from nominal to +0.07 mm over the run (its upper limit is +0.05,
so the last parts fail), each with its own noise seed. Then, in the same
run, times

- the baseline: one `inspect PART IMAGES -o OUT` process per part, one
  after the other (what a shell loop does);
- `inspect batch MANIFEST -o OUT` with the default workers (one per core),
  sampling the resident memory of its worker processes.

Prints parts per minute of each and their ratio, the CPU seconds each
spent per part (all their processes: on a machine shared with other jobs
the wall-clock ratio moves with the load, the CPU time much less), the
peak RSS per worker, and the batch's own check: the parts that fail, the tests the SPC page
fired on circle-4.diameter and its Cpk beside one computed here from the
database with numpy.
"""

import argparse
import csv
import os
import resource
import sqlite3
import subprocess
import sys
import threading
import time
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
PART = REPO / "examples" / "plate" / "part.step"
CHAR = "circle-4.diameter"
SHIFT_START = datetime(2000, 1, 1, 6, 0)  # the parts' synthetic time stamps, one a minute


def render_parts(n, folder, drift):
    """Render the N plates (skipping those already there); returns [(serial, images, deviation)]."""
    from partinspect.simulate.folder import render_to_folder

    parts = []
    for i, dev in enumerate(np.linspace(0.0, drift, n)):
        serial = f"P{i + 1:03d}"
        out = folder / serial
        if not (out / "images" / "right.png").is_file():
            t0 = time.perf_counter()
            render_to_folder(PART, out, noise=2.0, seed=100 + i, deviations=[f"{CHAR}={dev:.4f}"])
            print(f"rendered {serial} ({CHAR} {dev:+.4f} mm) in {time.perf_counter() - t0:.1f} s", flush=True)
        parts.append((serial, out / "images", dev))
    return parts


def _children_cpu():
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def shell_loop(parts, out):
    """Wall seconds and CPU seconds (the processes and the children they waited for) of the loop."""
    t0, c0 = time.perf_counter(), _children_cpu()
    for serial, images, _ in parts:
        subprocess.run([sys.executable, "-m", "partinspect", str(PART), str(images), "-o", str(out / serial), "-q"],
                       env=_env(), capture_output=True)
    return time.perf_counter() - t0, _children_cpu() - c0


def _env():
    return {**os.environ, "PYTHONPATH": str(REPO), "PARTINSPECT_PROGRESS": "0"}


def batch(parts, out, workers):
    import psutil

    manifest = out.parent / f"{out.name}.csv"
    with open(manifest, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["serial", "step", "images", "time"])
        for i, (serial, images, _) in enumerate(parts):
            w.writerow([serial, PART, images, (SHIFT_START + timedelta(minutes=i)).isoformat()])
    cmd = [sys.executable, "-m", "partinspect", "batch", str(manifest), "-o", str(out), "-q"]
    if workers:
        cmd += ["--workers", str(workers)]
    peak, cpu = {}, {}
    t0, c0 = time.perf_counter(), _children_cpu()
    proc = subprocess.Popen(cmd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    done = threading.Event()

    def sample():
        me = psutil.Process(proc.pid)
        while not done.is_set():
            try:
                for c in me.children(recursive=True):
                    peak[c.pid] = max(peak.get(c.pid, 0), c.memory_info().rss)
                    t = c.cpu_times()
                    cpu[c.pid] = t.user + t.system  # the workers' own; their children are sampled too
            except psutil.Error:
                pass
            time.sleep(0.5)

    t = threading.Thread(target=sample, daemon=True)
    t.start()
    _, err = proc.communicate()
    done.set()
    elapsed = time.perf_counter() - t0
    # The batch process itself (waited for here), and its workers and forkserver
    # as last sampled (they are not its waited children: up to 0.5 s each unseen).
    cpu_total = _children_cpu() - c0 + sum(cpu.values())
    # The forkserver holds only the package; the workers are the big ones.
    workers_rss = sorted(peak.values())[-(workers or os.cpu_count()):]
    return elapsed, proc.returncode, err.decode(), workers_rss, cpu_total


def check(out):
    con = sqlite3.connect(out / "results.sqlite")
    fails = [s for (s,) in con.execute("SELECT serial FROM parts WHERE verdict = 'fail' ORDER BY serial")]
    x = np.array([m for (m,) in con.execute(
        "SELECT c.measured FROM characteristics c JOIN parts p ON p.id = c.part_id "
        f"WHERE c.characteristic = '{CHAR}' AND c.measured IS NOT NULL ORDER BY p.measured_at")])
    rows = {r["characteristic"]: r for r in csv.DictReader(open(out / "spc.csv", newline=""))}
    sigma_w = np.mean(np.abs(np.diff(x))) * np.sqrt(np.pi) / 2
    cpk = min(12.05 - x.mean(), x.mean() - 12.0) / (3 * sigma_w)
    return fails, rows[CHAR], cpk


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=8, help="parts (default 8)")
    ap.add_argument("--drift", type=float, default=0.07, help="circle-4's diameter drift over the run, mm")
    ap.add_argument("--workers", type=int, default=None, help="batch workers (default: one per core)")
    ap.add_argument("--dir", default="/tmp/bench_batch", help="renders and outputs (renders are reused)")
    ap.add_argument("--no-baseline", action="store_true", help="skip the shell loop")
    args = ap.parse_args()
    root = Path(args.dir)
    parts = render_parts(args.n, root / "parts", args.drift)
    print(f"{args.n} plates, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}", flush=True)
    if not args.no_baseline:
        loop, loop_cpu = shell_loop(parts, root / "loop")
        print(f"shell loop of `inspect`: {loop:7.1f} s  {60 * args.n / loop:5.2f} parts/min  "
              f"{loop_cpu / args.n:5.2f} CPU s/part", flush=True)
    out = root / "batch"
    if out.exists():
        import shutil

        shutil.rmtree(out)
    elapsed, code, err, rss, cpu = batch(parts, out, args.workers)
    print(f"inspect batch:           {elapsed:7.1f} s  {60 * args.n / elapsed:5.2f} parts/min  "
          f"{cpu / args.n:5.2f} CPU s/part  (exit code {code})")
    if not args.no_baseline:
        print(f"speed-up: {loop / elapsed:.2f}x (CPU per part {loop_cpu / cpu:.2f}x less); "
              f"load average {os.getloadavg()[0]:.1f} at the end")
    print("peak RSS per worker: " + ", ".join(f"{r / 2**20:.0f} MB" for r in rss))
    if err.strip():
        print("stderr: " + err.strip())
    fails, row, cpk = check(out)
    print(f"failed parts: {', '.join(fails) or 'none'} (deviation above +0.05 mm from "
          f"P{1 + int(np.ceil(0.05 / args.drift * (args.n - 1))):03d} on)")
    print(f"{CHAR}: tests fired {row['tests'] or 'none'}; Cpk {float(row['cpk']):.4f} in spc.csv, "
          f"{cpk:.4f} from the database with numpy; Ppk {float(row['ppk']):.4f}; Q_MP {float(row['q_mp']):.1%}")


if __name__ == "__main__":
    main()
