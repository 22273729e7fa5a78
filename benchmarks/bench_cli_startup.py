"""Start-up time of `inspect --help` (target: under 0.5 s).

Prints the median of several runs beside the baseline of a bare
`python -c pass` and of `import cadquery`, measured in the same run.
"""

import statistics
import subprocess
import sys
import time


def median_seconds(cmd, runs):
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main():
    py = sys.executable
    rows = [
        ("python -c pass (baseline)", [py, "-c", "pass"], 9),
        ("inspect --help", [py, "-m", "partinspect", "--help"], 9),
        ("python -c 'import cadquery' (what --help avoids)", [py, "-c", "import cadquery"], 3),
    ]
    print(f"{'command':52s} median of runs")
    for name, cmd, runs in rows:
        print(f"{name:52s} {median_seconds(cmd, runs):6.3f} s ({runs} runs)")


if __name__ == "__main__":
    main()
