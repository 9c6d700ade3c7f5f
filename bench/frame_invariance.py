"""The margins of the closed-loop frame-invariance tests, measured.

``tests/test_frame_invariance.py`` samples TrafficBots WOSAC rollouts on a scene and on a
rigidly moved copy of it and checks that the futures, mapped back, agree. What is left between
the two is float rounding that the closed loop amplifies, and that rounding differs between
CPUs (SIMD width, numpy's and torch's kernel dispatch, libm). This script measures, on the
test's scenes and settings, the per agent-rollout deviation (max over the 80 steps, metres):

* under every kernel path that can be forced on this machine (``ATEN_CPU_CAPABILITY`` and
  ``NPY_DISABLE_CPU_FEATURES``; one process each), the move alone: what the tests must accept;
* under injected frame bugs, the smallest the tests must still catch: the moved copy's
  headings off by a few mrad (a heading channel that depends on the world frame), or its
  tracks off by a few centimetres against its map (a position that depends on it).

It prints one table (share within 5 cm, 10 cm, 50 cm; median, p90, p99, max).

    python bench/frame_invariance.py [--data DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data" / "womd"

KERNEL_PATHS = {
    "native": {},
    "aten avx2, numpy x86-64-v3": {
        "ATEN_CPU_CAPABILITY": "avx2",
        "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR",
    },
    "aten default, numpy baseline": {
        "ATEN_CPU_CAPABILITY": "default",
        "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR",
    },
}
"""Environment of each kernel path (features a CPU lacks are ignored by numpy)."""
BUGS = {
    "heading +1 mrad": ("heading", 1e-3),
    "heading +5 mrad": ("heading", 5e-3),
    "tracks +2 cm": ("offset", 0.02),
    "tracks +10 cm": ("offset", 0.10),
}
"""Injected frame bugs: (kind, size in rad or metres), applied to the moved copy only."""


def _deviations(scene_name: str, bug: tuple[str, float] | None, data: Path) -> list[float]:
    """Per agent-rollout deviation (metres) of the test's rollouts on one scene."""
    import dataclasses

    import numpy as np

    os.environ["TBSIM_WOMD_DIR"] = str(data)
    sys.path.insert(0, str(REPO))
    from policies.trafficbots.wosac import load_default_model, trafficbots_rollouts
    from tbsim_env.data.generator import generate_scenario
    from tbsim_env.data.loader import load_scenarios
    from tests import test_frame_invariance as t

    if scene_name == "real":
        scene = load_scenarios(data / "waymo-open-dataset" / "motion_data_one_scenario.tfrecord")[0]
    else:
        scene = generate_scenario(*t.GENERATED)
    moved = t.moved(scene)
    if bug is not None:
        kind, size = bug
        tr = moved.tracks
        if kind == "heading":
            tr = dataclasses.replace(tr, heading=np.where(tr.valid, tr.heading + size, tr.heading))
        else:
            xyz = tr.xyz.copy()
            xyz[..., 0] += np.where(tr.valid, size, 0.0)
            tr = dataclasses.replace(tr, xyz=xyz)
        moved = moved.replace(tracks=tr)
    model = load_default_model()
    kw = dict(num_rollouts=t.KEPT, num_samples=t.SAMPLES, seed=0)
    a = trafficbots_rollouts(model, scene, **kw)
    b = trafficbots_rollouts(model, moved, **kw)
    x, y = t.map_back(b.x.numpy(), b.y.numpy())
    return np.hypot(x - a.x.numpy(), y - a.y.numpy()).max(-1).ravel().tolist()


def _child(args: argparse.Namespace) -> None:
    import torch

    torch.set_num_threads(1)
    bugs = [None] if args.bugs == "none" else list(BUGS.values())
    out = {
        scene: [_deviations(scene, bug, args.data) for bug in bugs]
        for scene in ("real", "generated")
    }
    print(json.dumps(out))


def _row(name: str, dev: list[float]) -> str:
    import numpy as np

    d = np.asarray(dev)
    within = [f"{(d <= tol).mean():6.3f}" for tol in (0.05, 0.10, 0.50)]
    q = [f"{v:7.3f}" for v in np.quantile(d, [0.5, 0.9, 0.99])]
    return f"| {name:34s} | {len(d):4d} | {' | '.join(within)} | {' | '.join(q)} | {d.max():6.2f} |"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default_data = Path(os.environ.get("TBSIM_WOMD_DIR", DEFAULT_DATA))
    p.add_argument("--data", type=Path, default=default_data)
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--bugs", default="none", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        _child(args)
        return
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from machine import measure

    print(measure().line())  # accuracy, not speed: the line says where it was measured
    runs: dict[str, dict] = {}
    jobs = [(name, env, "none") for name, env in KERNEL_PATHS.items()]
    jobs.append(("native", {}, "all"))
    for name, env, bugs in jobs:
        cmd = [sys.executable, __file__, "--child", "--bugs", bugs, "--data", str(args.data)]
        res = subprocess.run(cmd, env={**os.environ, **env}, capture_output=True, text=True)
        if res.returncode:
            raise SystemExit(res.stderr)
        runs[f"{name}/{bugs}"] = json.loads(res.stdout.strip().splitlines()[-1])
    head = "| scene, case | n | <=5 cm | <=10 cm | <=50 cm | median m | p90 m | p99 m | max m |"
    print(head + "\n|" + "---|" * 9)
    for scene in ("real", "generated"):
        for name in KERNEL_PATHS:
            print(_row(f"{scene}, move only, {name}", runs[f"{name}/none"][scene][0]))
        for k, bug in enumerate(BUGS):
            print(_row(f"{scene}, bug: {bug}", runs["native/all"][scene][k]))


if __name__ == "__main__":
    main()
