#!/usr/bin/env python3
"""Inference time of the VFA CNN (``VfaUNet``) against its widths, with random weights (capacity planning).

Run after ``source scripts/env.sh``:  ``python bench/bench_vfa_cnn_widths.py [--samples N] [--rounds R]
[--backends onnxruntime,torch] [--widths 8,16,32/32,16,8 8,16,32/32,16,16+h2 ...]``. Prints a markdown table on stdout.

For each width (encoder channels / decoder channels; the fully connected layer 256 wide) an untrained
network is built once and given to a ``CnnFootholdSelector`` per backend (no verification); on ``--samples``
terrains of ``bench_vfa.make_cases`` we time ``select_legs`` for the 4 legs (time per leg = call / 4) and
for one leg, in ``--rounds`` rounds that visit every (width, backend) in turn; median and p99 [ms]. One
thread. The weights only change the decode's work a little, so random ones are fine for timing.
A benchmark, never a test.
"""

from __future__ import annotations

import argparse
import sys
import time

import torch
from bench_vfa import make_cases
from common import VITAL_STATS, latency_stats  # bench/common.py

from tal_core.legs import LEGS
from tal_core.robot_model import RobotModel
from tal_perception.fec import FootholdEvaluator
from tal_perception.vfa_cnn import CnnFootholdSelector, FootholdRequest, NetConfig, build_net, load_model

DEFAULT_WIDTHS = ["8,16,32/32,16,8", "8,16,32/32,16,16", "16,32,64/64,32,16", "24,48,96/96,48,24"]


def parse_width(text: str) -> tuple[tuple[int, ...], tuple[int, ...], bool, int]:
    """(encoder widths, decoder widths, roughness features, head blocks) of "8,16,32/32,16,8[+r][+hN]" (+r:
    ``NetConfig``'s ``roughness_features``; +hN: N ``head_blocks``)."""
    widths, *options = text.split("+")
    unknown = [o for o in options if o != "r" and not (o.startswith("h") and o[1:].isdigit())]
    if unknown:
        raise SystemExit(f"--widths {text!r}: unknown option(s) {unknown} (known: +r, +hN)")
    encoder, decoder = widths.split("/")
    roughness = "r" in options
    blocks = next((int(o[1:]) for o in options if o.startswith("h")), 0)
    return tuple(int(c) for c in encoder.split(",")), tuple(int(c) for c in decoder.split(",")), roughness, blocks


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--samples", type=int, default=100, help="terrains")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seed", type=int, default=20240601)
    parser.add_argument("--backends", default="onnxruntime,torch")
    parser.add_argument("--widths", nargs="+", default=DEFAULT_WIDTHS,
                        help="encoder/decoder[+r][+hN], e.g. 8,16,32/32,16,8 (+r: with the roughness features, "
                        "+h2: 2 residual 1 x 1 head blocks)")  # fmt: skip
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = RobotModel.from_name("hyq")
    evaluator = FootholdEvaluator(model)
    encoding = load_model().config.encoding
    selectors = {}
    for text in args.widths:
        channels, decoder, roughness, blocks = parse_width(text)
        net = build_net(NetConfig(channels, 256, True, encoding, "unet", decoder, roughness, blocks)).eval()
        parameters = sum(p.numel() for p in net.parameters())
        for backend in args.backends.split(","):
            selector = CnnFootholdSelector(evaluator, net, verify=False, backend=backend)
            if selector.backend != backend:
                raise SystemExit(f"backend {backend} not available")
            selectors[(text, backend)] = (selector, parameters)
    cases = make_cases(model, args.samples, args.seed)
    requests = [[FootholdRequest(leg, c["nominal"], c["hip"], c["twist"], c["gait"]) for leg in LEGS] for c in cases]
    times: dict[tuple[str, str], dict[str, list[float]]] = {k: {"batch": [], "one": []} for k in selectors}
    for _ in range(args.rounds):
        for key, (selector, _) in selectors.items():
            selector.select_legs(requests[0], cases[0]["grid"], yaw=cases[0]["grid"].yaw)  # warm-up
            for case, batch in zip(cases, requests):
                start = time.perf_counter()
                selector.select_legs(batch, case["grid"], yaw=case["grid"].yaw)
                times[key]["batch"].append((time.perf_counter() - start) / len(LEGS) * 1e3)
            for case, batch in zip(cases, requests):
                start = time.perf_counter()
                selector.select_legs(batch[:1], case["grid"], yaw=case["grid"].yaw)
                times[key]["one"].append((time.perf_counter() - start) * 1e3)
    print("| widths (encoder / decoder) | parameters | backend | 4-leg batch per leg: median (p99) [ms] | "
          "one leg per call: median (p99) [ms] |")  # fmt: skip
    print("| --- | --- | --- | --- | --- |")
    for (text, backend), (_, parameters) in selectors.items():
        b, o = (latency_stats(times[(text, backend)][key], VITAL_STATS) for key in ("batch", "one"))
        print(f"| {text} | {parameters:,} | {backend} | {b['median']:.3f} ({b['p99']:.3f}) | "
              f"{o['median']:.3f} ({o['p99']:.3f}) |")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
