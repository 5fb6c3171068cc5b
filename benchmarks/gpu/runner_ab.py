"""Time the UDN runner of another commit against this tree's, interleaved, on one device.

    python -m benchmarks.gpu.runner_ab --base COMMIT [--device cuda] [--iters 100] [--rounds 5]

Reads ``recon/udn/runner.py`` of ``--base`` with ``git show`` (the rest of the package is this
tree's, so the base's runner must still import against it), builds both runners on the real
pairs' geometry at full resolution (``bench udn``'s ``rgb-270x480`` case, synthetic data, the
default network, seed 0), warms each up for 5 iterations, then times ``--iters`` iterations of
each in turn for ``--rounds`` rounds (the order alternating) and prints the medians as JSON,
with the largest difference between the two final estimates relative to their peak (0 on a
CPU, where both do the same arithmetic; on a GPU cuDNN's kernels are not deterministic by
default, so there the two drift apart).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any


def load_base_runner(commit: str) -> Any:
    """The module ``recon/udn/runner.py`` as it was at ``commit``."""
    root = Path(__file__).resolve().parents[2]
    src = subprocess.run(["git", "show", f"{commit}:recon/udn/runner.py"], cwd=root,
                         capture_output=True, text=True, check=True).stdout
    path = Path(tempfile.mkdtemp()) / "runner_base.py"
    path.write_text(src, encoding="utf-8")
    spec = importlib.util.spec_from_file_location("runner_base", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["runner_base"] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--base", required=True, help="the commit whose runner is compared")
    p.add_argument("--device", default="cuda")
    p.add_argument("--iters", type=int, default=100)
    p.add_argument("--rounds", type=int, default=5)
    args = p.parse_args(argv)
    import numpy as np
    import torch

    import recon.udn.runner as this
    from benchmarks.bench_udn import CASES, _problem
    from recon.udn.network import NetworkConfig

    base = load_base_runner(args.base)
    dev = torch.device(args.device)
    model, b = _problem(CASES["rgb-270x480"], dev)
    net = NetworkConfig()

    def sync() -> None:
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    runners = {f"base ({args.base})": base.UDNRunner(model, b, network=net,
                                                      config=base.UDNConfig(seed=0)),
               "this tree": this.UDNRunner(model, b, network=net, config=this.UDNConfig(seed=0))}
    for r in runners.values():
        for _ in range(5):
            r.step()
    times: dict[str, list[float]] = {k: [] for k in runners}
    for rnd in range(args.rounds):
        for k in (list(runners) if rnd % 2 == 0 else list(runners)[::-1]):
            sync()
            t = time.perf_counter()
            for _ in range(args.iters):
                runners[k].step()
            sync()
            times[k].append((time.perf_counter() - t) / args.iters)
    a, c = runners.values()
    ea, ec = a.final_estimate(), c.final_estimate()
    out: dict[str, Any] = {k: {"median_ms": 1e3 * statistics.median(v),
                               "rounds_ms": [round(1e3 * x, 2) for x in v]}
                           for k, v in times.items()}
    out["iterations_each"] = 5 + args.rounds * args.iters
    out["max_rel_diff_of_estimates"] = float(np.abs(ea - ec).max() / np.abs(ea).max())
    out["device"] = this.describe_device(dev)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
