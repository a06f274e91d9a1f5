#!/usr/bin/env python3
"""Do the VFA CNN's network runtimes select the same candidates? (ONNX Runtime vs torch fast path vs plain.)

Run after ``source scripts/env.sh``:  ``python bench/compare_vfa_cnn_backends.py [--weights F] [--data D]``.
On the protocol's test set (``<data>/test_seed2_n4401.npz``, made by ``python -m tal_lab.vital.eval_vfa``),
``CnnFootholdSelector.predict`` (batches of 256, no verification) with the weights' stored decode and with the
argmax, once per backend; prints each run's time and how many of the tuples' selections differ between them.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from tal_lab.vital.eval_vfa import predict_all
from tal_lab.vital.vfa_dataset import VfaDataset

from tal_core.robot_model import RobotModel
from tal_perception.fec import FootholdEvaluator
from tal_perception.vfa_cnn import DEFAULT_WEIGHTS, CnnFootholdSelector, load_model
from tal_perception.vfa_decode import VfaDecode


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", type=Path, default=DEFAULT_WEIGHTS)
    parser.add_argument("--data", type=Path, default=Path("data/vfa/test_seed2_n4401.npz"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    evaluator = FootholdEvaluator(RobotModel.from_name("hyq"))
    data = VfaDataset.load(args.data)
    net = load_model(args.weights)
    runs = {"onnxruntime": {"backend": "onnxruntime"}, "torch_fast": {"backend": "torch"},
            "torch_plain": {"backend": "torch", "fast": False}}  # fmt: skip
    for decode in (None, VfaDecode("argmax")):
        selections = {}
        for name, options in runs.items():
            selector = CnnFootholdSelector(evaluator, net, verify=False, decode=decode, **options)
            if selector.backend != options["backend"]:
                raise SystemExit(f"{name}: backend {options['backend']} not available")
            start = time.perf_counter()
            selections[name] = predict_all(selector, data)
            print(f"{name}: {time.perf_counter() - start:.1f} s", file=sys.stderr)
        mode = (decode or net.decode).mode
        pairs = [("onnxruntime", "torch_fast"), ("onnxruntime", "torch_plain"), ("torch_fast", "torch_plain")]
        counts = ", ".join(f"{a} vs {b}: {int((selections[a] != selections[b]).sum())}" for a, b in pairs)
        print(f"decode {mode}, {len(data)} tuples; selections that differ: {counts}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
