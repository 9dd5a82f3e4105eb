"""Fits the train-step cost model of ``train.auto_fit`` to steps measured on a card, and checks it.

  python benchmarks/cost_model.py --rates h200 --out benchmarks/results/h200/cost_model.json \
      --point dots-unrolled /tmp/dots.hlo 607.0 --point none2-unrolled /tmp/none2.hlo 552.9 ...

Each point is a setting's name, the optimized HLO of its step compiled for the card
(``benchmarks/hlo_ops.py --save_hlo``, no hardware needed) and the step's median milliseconds
measured on the card (``benchmarks/train_step.py``). :func:`wmjax.train.fit.predicted_step_s`
prices a step as its matmul FLOPs over a fraction of the card's peak plus the bytes its other
kernels move over a fraction of its bandwidth; this script fits those two fractions by least
squares and prints every point's measured, predicted (with the package's fractions and with the
fitted ones) and the error. The JSON keeps each point's cost, so ``tests/test_fit.py`` checks the
package's fractions against the measurements without the HLO.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from wmjax.train import fit, hlo_cost


def fit_efficiencies(costs: list[dict], step_s: list[float], rates: tuple[float, float]
                     ) -> tuple[float, float]:
  """(matmul, bandwidth) fractions of ``rates`` that predict ``step_s`` best (least squares in
  seconds over the points' ``costs``)."""
  flops, bandwidth = rates
  design = np.array([[c["matmul_flops"] / flops, c["other_bytes"] / bandwidth] for c in costs])
  inverse, *_ = np.linalg.lstsq(design, np.array(step_s), rcond=None)
  return 1 / inverse[0], 1 / inverse[1]


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--rates", required=True, choices=sorted(fit.DEVICE_RATES),
                      help="the card the steps were measured on")
  parser.add_argument("--point", nargs=3, action="append", required=True,
                      metavar=("NAME", "HLO", "MS"), help="a setting, its HLO text, its step ms")
  parser.add_argument("--out", default=None, help="write the points and the fit here")
  args = parser.parse_args()
  rates = fit.DEVICE_RATES[args.rates]
  points = []
  for name, path, ms in args.point:
    with open(path) as f:
      points.append({"name": name, "step_ms": float(ms), "cost": hlo_cost.step_cost(f.read())})
  matmul, bandwidth = fit_efficiencies([p["cost"] for p in points],
                                       [p["step_ms"] / 1e3 for p in points], rates)
  print(f"fitted: matmul {matmul:.3f} of peak, other kernels {bandwidth:.3f} of bandwidth "
        f"(package: {fit.MATMUL_EFFICIENCY}, {fit.BANDWIDTH_EFFICIENCY})")
  print(f"{'setting':<26}{'TFLOP':>8}{'GB':>8}{'measured':>10}{'package':>9}{'error':>8}")
  for p in points:
    p["predicted_ms"] = 1e3 * fit.predicted_step_s(p["cost"], rates)
    error = p["predicted_ms"] / p["step_ms"] - 1
    print(f"{p['name']:<26}{p['cost']['matmul_flops'] / 1e12:>8.1f}"
          f"{p['cost']['other_bytes'] / 1e9:>8.1f}{p['step_ms']:>10.1f}{p['predicted_ms']:>9.1f}"
          f"{100 * error:>7.1f}%")
  if args.out:
    with open(args.out, "w") as f:
      json.dump({"rates": args.rates, "fitted_matmul_efficiency": matmul,
                 "fitted_bandwidth_efficiency": bandwidth, "points": points}, f, indent=1)
      f.write("\n")


if __name__ == "__main__":
  main()
