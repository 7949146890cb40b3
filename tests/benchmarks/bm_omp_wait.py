"""What OpenMP's wait policy costs a library user on a busy machine (issue 45, item 5).

The same render (forward + backward, 100k Gaussians at 504x378, 2 threads) in a fresh process
three ways, alternating, while ``--load`` busy processes keep the machine loaded:

* ``torch first``: ``import torch`` before ``import cobgs``, the variable unset: the OpenMP
  runtime starts with its default (spinning) policy, as before cobgs set it;
* ``cobgs first``: ``import cobgs`` first, the variable unset: cobgs sets PASSIVE before torch
  loads the runtime (what a plain library user now gets);
* ``env PASSIVE``: ``OMP_WAIT_POLICY=PASSIVE`` in the environment (what the CLI and the tests set).

Run (not collected by pytest)::

    .venv/bin/python tests/benchmarks/bm_omp_wait.py [--load 5] [--rounds 5] [--reps 5]

Prints per way the median over rounds of the per-process median render time, and the ratio
to ``env PASSIVE``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

CHILD = r"""
import json, sys, time
order = sys.argv[1]
if order == "torch":
    import torch, cobgs
else:
    import cobgs, torch
from cobgs.render.selfcheck import random_scene, _render
torch.set_num_threads(2)
scene = {k: (v.float() if torch.is_tensor(v) else v) for k, v in random_scene(100_000, 504, 378, seed=5).items()}
_render(scene, "native")  # warm-up (extension load)
times = []
for _ in range(int(sys.argv[2])):
    t = time.perf_counter()
    _render(scene, "native")
    times.append(time.perf_counter() - t)
import os
print(json.dumps({"policy": os.environ.get("OMP_WAIT_POLICY"), "times": times}))
"""

BUSY = "import time\nwhile True:\n    x = sum(i * i for i in range(10000))\n"


def run_way(way: str, reps: int) -> tuple[float, str]:
    env = dict(os.environ, OMP_NUM_THREADS="2", PYTHONPATH=str(ROOT))
    env.pop("OMP_WAIT_POLICY", None)
    order = "torch" if way == "torch first" else "cobgs"
    if way == "env PASSIVE":
        env["OMP_WAIT_POLICY"] = "PASSIVE"
    out = subprocess.run([sys.executable, "-c", CHILD, order, str(reps)], env=env, capture_output=True, text=True,
                         check=True, cwd=ROOT).stdout
    rec = json.loads(out.strip().splitlines()[-1])
    return statistics.median(rec["times"]), str(rec["policy"])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--load", type=int, default=5, help="busy processes beside the renders")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args()
    ways = ("torch first", "cobgs first", "env PASSIVE")
    busy = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(args.load)]
    res: dict = {w: [] for w in ways}
    policy: dict = {}
    try:
        time.sleep(2)
        for r in range(args.rounds):
            for w in (ways if r % 2 == 0 else ways[::-1]):
                t, policy[w] = run_way(w, args.reps)
                res[w].append(t)
            print(f"round {r + 1}: " + ", ".join(f"{w} {1e3 * res[w][-1]:.0f} ms" for w in ways)
                  + f" (load {os.getloadavg()[0]:.1f})", flush=True)
    finally:
        for p in busy:
            p.kill()
    ref = statistics.median(res["env PASSIVE"])
    print(f"\nfwd + bwd, 100k Gaussians, 504x378, 2 threads, {args.load} busy processes beside; median of "
          f"{args.rounds} rounds of the per-process median of {args.reps}:")
    print("| way | OMP_WAIT_POLICY seen by the child | ms | ratio to env PASSIVE |\n|---|---|---|---|")
    for w in ways:
        m = statistics.median(res[w])
        print(f"| {w} | {policy[w]} | {1e3 * m:.0f} | {m / ref:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
