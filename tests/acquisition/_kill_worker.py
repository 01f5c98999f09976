"""Subprocess of the kill test: acquire (or resume) a run, printing each committed line.

Usage: python -m tests.acquisition._kill_worker RUN.h5
"""

from __future__ import annotations

import sys

from acquisition import run_sweep
from tests.acquisition._common import DRIVE, SENSORS, plan, plant3
from tests.acquisition.backends import make_sim_driver


def main(path: str) -> None:
    print("READY", flush=True)

    def on_line(f, frf, q):  # called after the line is committed to the file
        print(f"LINE {f!r}", flush=True)

    run_sweep(make_sim_driver(plant3()), plan(), path, sensors=SENSORS, drive=DRIVE, level_n=1.0, on_line=on_line)
    print("DONE", flush=True)


if __name__ == "__main__":
    main(sys.argv[1])
