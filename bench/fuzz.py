"""The pipeline fuzz at scale: bad values inside valid real files, every case through load,
both environments, WOSAC export and scoring (``tests/test_fuzz_pipeline.py``'s cases).

Each case must be refused with one ``TbsimError`` line naming its file, or run with finite
outputs. Anything else (another exception, a non-finite output, an error not naming the file,
a case over its time limit) is a failure, printed with its case number; the cases depend only
on the seed. Prints the tally, the wall time and the machine.

    python bench/fuzz.py [--cases 10000] [--seed 20250828] [--data DIR]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from machine import measure  # noqa: E402

from tests.pipeline_support import run_pipeline  # noqa: E402
from tests.test_bad_input import time_guard  # noqa: E402
from tests.test_fuzz_pipeline import CASE_LIMIT_S, run_fuzz  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", type=int, default=10_000)
    p.add_argument("--seed", type=int, default=20250828)
    default = os.environ.get("TBSIM_WOMD_DIR", str(REPO.parent / "shared" / "data" / "womd"))
    p.add_argument("--data", type=Path, default=Path(default))
    args = p.parse_args()
    torch.set_num_threads(1)
    failures: list[str] = []
    bar = tqdm(total=args.cases, unit="case")

    def one(case: int, path: Path) -> str:
        bar.update(1)
        try:
            with time_guard(CASE_LIMIT_S), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return run_pipeline(path)
        except BaseException as err:  # noqa: BLE001 - every failure is reported, the run goes on
            if isinstance(err, KeyboardInterrupt):
                raise
            failures.append(f"case {case}: {type(err).__name__}: {' '.join(str(err).split())}")
            return "failed"

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        outcomes = run_fuzz(args.cases, args.seed, Path(tmp), args.data, on_case=one)
    bar.close()
    wall = time.perf_counter() - t0
    tally = ", ".join(f"{k} {len(v)}" for k, v in sorted(outcomes.items()))
    print(f"{args.cases} cases (seed {args.seed}) in {wall:.0f} s: {tally}")
    print(measure().line())
    for line in failures[:50]:
        print(line)
    raise SystemExit(1 if failures else 0)


if __name__ == "__main__":
    main()
