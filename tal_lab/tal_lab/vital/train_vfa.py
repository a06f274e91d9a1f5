"""Train the CNN approximation of the VFA's foothold evaluation (``vfa_cnn``) on exact FEC labels.

    python -m tal_lab.vital.train_vfa --out tal_perception/tal_perception/models [--data data/vfa] [--seed 1]

Steps: (1) the labelled set (``vfa_dataset``; cached as ``<data>/train_seed<seed>_n<count>.npz``, a
cache with more samples of the same seed is reused); (2) a seeded 9:1 split into training and validation
(thesis: validation-based early stopping with a 9-to-1 proportion), each completed with its y-mirror
(left <-> right legs); samples without a safe candidate are left out (the CNN cannot output "none");
(3) Adam with a cosine decay over ``--epochs``, mini-batches of 64; the loss is the cross-entropy of the
optimum logits against the exact optimum (softened with ``--soft-target``, see ``optimum_target``) plus
``--safe-weight`` x the binary cross-entropy of the safe-mask logits against the exact safe mask;
(4) the epoch with the best validation perfect-match rate (``--select-on argmax``, the thesis' decode; or,
with ``--select-on combined``, the best perfect match + safe rate of the combined decode with
``--select-safe-weight``, the decode the shipped weights use) is saved as ``<out>/vfa_cnn.pt`` (float16)
with ``<out>/vfa_cnn_training.json`` (settings, data statistics, history). One CPU thread by default.
The decode (``vfa_decode``) is chosen afterwards on a separate tuning set: ``tune_vfa_decode --store``.

Fine-tuning: ``--init-weights <file>`` starts from saved weights (their architecture replaces the
architecture options; the encoding must match), scores them as "epoch 0" on the validation set and keeps
them unless an epoch beats their validation perfect match. ``--extra-seeds 4 ...`` adds training sets of
other seeds (``<data>/train_seed<s>_n<count>.npz``, labelled when missing); each set is split 9:1 with its
own seed, so the validation part of the ``--seed`` set is the same as in a run without extra seeds (weights
trained on it never see its validation tuples).

Departures from the thesis' training (Adam at 1e-3, plain cross-entropy), chosen on short pilots on a
quarter of the data (see ``docs/models/VFA_CARD.md``) because the thesis settings left the network at the class
prior (the nominal) within our CPU budget: learning rate 3e-3 with cosine decay, the auxiliary safe-mask
output (weight 1; 10 and 3 scored lower) and half of the target mass spread over the safe cells near the
optimum's distance; the ``unet`` architecture (``VfaUNet``: the thesis' trunk plus a full-resolution
decoder; 69.9 % validation perfect match against 58.2 % for the thesis' ``VfaNet`` in the 4-epoch pilot
on 12,000 tuples per leg). Defaults: 48,000 tuples per leg, the ``unet``, 8 epochs, early stopping after
3 epochs without a better validation perfect match (about 9 min per epoch on one thread on this
machine, shared); ``--architecture thesis --epochs 10`` trains the previous model.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from tal_core.robot_model import RobotModel
from tal_lab.vital.vfa_dataset import (
    VfaDataset,
    cache_path,
    canonical_legs,
    load_or_generate,
    mirrored,
    mix_description,
    set_prefix,
)
from tal_perception.fec import FootholdEvaluator
from tal_perception.vfa_cnn import (
    ARCHITECTURES,
    EncodingConfig,
    NetConfig,
    VfaNet,
    VfaUNet,
    build_net,
    encode,
    load_model,
    save_model,
)
from tal_perception.vfa_decode import VfaDecode, decode

LOG = logging.getLogger("tal_lab.vital.train_vfa")
SELECTIONS = ("argmax", "combined")  # --select-on: how the kept epoch is chosen (see selection_score)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m tal_lab.vital.train_vfa", description=__doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )  # fmt: skip
    parser.add_argument("--out", type=Path, required=True, help="folder of vfa_cnn.pt and vfa_cnn_training.json")
    parser.add_argument("--data", type=Path, default=Path("data/vfa"), help="dataset cache folder")
    parser.add_argument("--robot", default="hyq", help="robot name or YAML (tal_core.robot_model)")
    parser.add_argument("--seed", type=int, default=1, help="seed of the data, the split and the weights")
    parser.add_argument("--samples-per-leg", type=int, default=48000, help="labelled tuples per leg")
    parser.add_argument("--epochs", type=int, default=8, help="length of the learning-rate schedule [epochs]")
    parser.add_argument(
        "--patience", type=int, default=3,
        help="early stopping: stop after this many epochs without a better validation perfect match (0: never)",
    )  # fmt: skip
    parser.add_argument(
        "--max-training-s", type=float, default=0.0,
        help="time budget [s]: no epoch is started that would end after it (last epoch's duration; 0: none)",
    )  # fmt: skip
    parser.add_argument("--warmup", type=float, default=0.0, help="linear learning-rate warm-up [epochs]")
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--lr", type=float, default=3e-3, help="Adam learning rate at the start (thesis: 1e-3)")
    parser.add_argument("--val-fraction", type=float, default=0.1)
    parser.add_argument("--safe-weight", type=float, default=1.0, help="weight of the safe-mask loss (0: no head)")
    parser.add_argument(
        "--soft-target", type=float, default=0.5, metavar="M",
        help="mix M of a soft target into the one-hot optimum: the safe cells weighted by exp(-(d^2 - d_opt^2) / "
        "--soft-cells2), d the distance from the nominal [cells] (denser gradients; its argmax is still g)",
    )  # fmt: skip
    parser.add_argument("--soft-cells2", type=float, default=4.0, help="temperature of the soft target [cells^2]")
    parser.add_argument("--channels", type=int, nargs=3, default=[8, 16, 32], help="conv layer widths")
    parser.add_argument("--hidden", type=int, default=256, help="width of the first fully connected layer")
    parser.add_argument(
        "--architecture", choices=ARCHITECTURES, default="unet",
        help="thesis: VfaNet (conv trunk + fully connected output); unet: VfaUNet (full-resolution decoder)",
    )  # fmt: skip
    parser.add_argument("--decoder-channels", type=int, nargs=3, default=[32, 16, 8],
                        help="unet: decoder widths at 9, 17 and 33 cells")  # fmt: skip
    parser.add_argument(
        "--roughness-features", action="store_true",
        help="unet: the last decoder layer also reads the FEC's roughness statistics (vfa_cnn.RoughnessFeatures)",
    )  # fmt: skip
    parser.add_argument("--head-blocks", type=int, default=0,
                        help="unet: residual 1 x 1 blocks per candidate after the last decoder layer")  # fmt: skip
    parser.add_argument("--no-mirror", action="store_true", help="do not add the y-mirrored samples")
    parser.add_argument(
        "--canonical-legs", action="store_true",
        help="train on left legs only, each right-leg tuple replaced by its y-mirror (NetConfig.canonical_legs: "
        "the selector mirrors right legs in and out); instead of adding the mirrors",
    )  # fmt: skip
    parser.add_argument(
        "--init-weights", type=Path, default=None,
        help="start from these weights (fine-tuning; their architecture is used, epoch 0 = them on validation)",
    )  # fmt: skip
    parser.add_argument(
        "--extra-seeds", type=int, nargs="+", default=[],
        help="more training sets of these seeds (same --samples-per-leg), each split 9:1 with its own seed",
    )  # fmt: skip
    parser.add_argument(
        "--wide-seeds", type=int, nargs="+", default=[],
        help="more training sets of these seeds sampled with the wide hip range (vfa_dataset.HIP_RANGES, cached as "
        "train_wide_seed<s>_n<count>.npz), each split 9:1 with its own seed",
    )  # fmt: skip
    parser.add_argument("--wide-samples-per-leg", type=int, default=32000, help="labelled tuples per leg of a wide set")
    parser.add_argument(
        "--select-on", choices=SELECTIONS, default="argmax",
        help="which epoch is kept: argmax = best validation perfect match of the optimum head's argmax; combined "
        "= best perfect match + safe rate of the combined decode (optimum logit + λ log p_safe, needs the safe head)",
    )  # fmt: skip
    parser.add_argument("--select-safe-weight", type=float, default=2.0,
                        help="λ of the combined decode that --select-on combined scores")  # fmt: skip
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = parser.parse_args(argv)
    if args.select_on == "combined" and (args.safe_weight <= 0.0 or not args.select_safe_weight >= 0.0):
        parser.error("--select-on combined needs the safe head (--safe-weight > 0) and --select-safe-weight >= 0")
    if args.samples_per_leg < 10 or args.epochs < 1 or not 0.0 < args.val_fraction < 0.5:
        parser.error("need --samples-per-leg >= 10, --epochs >= 1 and 0 < --val-fraction < 0.5")
    if args.patience < 0 or not 0.0 <= args.warmup < args.epochs or not args.max_training_s >= 0.0:
        parser.error("need --patience >= 0, 0 <= --warmup < --epochs and --max-training-s >= 0")
    if args.seed in args.extra_seeds or len(set(args.extra_seeds)) != len(args.extra_seeds):
        parser.error("--extra-seeds must differ from --seed and from each other")
    if len(set(args.wide_seeds)) != len(args.wide_seeds) or args.wide_samples_per_leg < 10:
        parser.error("--wide-seeds must differ from each other and --wide-samples-per-leg be >= 10")
    if args.canonical_legs and args.no_mirror:
        parser.error("--canonical-legs replaces the mirrored samples: it cannot be combined with --no-mirror")
    if {2, 3} & set(args.extra_seeds + args.wide_seeds) or args.seed in (2, 3):
        parser.error("seeds 2 (the protocol's test set) and 3 (the decode tuning set) must not be trained on")
    return args


class Batches:
    """Encoded mini-batches of a dataset's samples that have a safe candidate."""

    def __init__(self, data: VfaDataset, encoding: EncodingConfig) -> None:
        self.data = data.subset(data.label >= 0)
        self.encoding = encoding

    def __len__(self) -> int:
        return len(self.data)

    def tensors(self, index: np.ndarray) -> tuple[torch.Tensor, ...]:
        d = self.data
        image, scalars = encode(self.encoding, d.heights[index], d.hip_height_m[index], d.twist[index], d.gait[index],
                                d.leg[index])  # fmt: skip
        safe = torch.from_numpy(d.safe[index].reshape(index.size, -1).astype(np.float32))
        label = torch.from_numpy(d.label[index].astype(np.int64))
        image = torch.from_numpy(image).contiguous(memory_format=torch.channels_last)  # ~20 % faster convs on CPU
        return image, torch.from_numpy(scalars), label, safe


def split(
    data: VfaDataset, val_fraction: float, seed: int, mirror: bool, canonical: bool = False
) -> tuple[VfaDataset, VfaDataset]:
    """Seeded train / validation split of the tuples, then each part completed with its mirror, or with
    ``canonical`` put in the frame of the left legs (``canonical_legs``: the same tuples, each once)."""
    order = np.random.default_rng([seed, 7]).permutation(len(data))
    n_val = int(round(val_fraction * len(data)))
    parts = [data.subset(np.sort(order[n_val:])), data.subset(np.sort(order[:n_val]))]
    if canonical:
        parts = [canonical_legs(p) for p in parts]
    elif mirror:
        parts = [VfaDataset.concatenate([p, mirrored(p)]) for p in parts]
    return parts[0], parts[1]


def training_sets(
    args: argparse.Namespace, evaluator: FootholdEvaluator
) -> tuple[VfaDataset, VfaDataset, dict[str, object]]:
    """Training and validation sets (mirrored unless ``--no-mirror``) and the statistics of all tuples: the
    ``--seed`` set, each ``--extra-seeds`` set and each ``--wide-seeds`` set (hip range "wide"; labelled or
    read from ``--data``) split 9:1 with its own seed, the parts concatenated in that order."""
    parts, sets = [], []
    sources = [(seed, "standard", args.samples_per_leg) for seed in [args.seed, *args.extra_seeds]]
    sources += [(seed, "wide", args.wide_samples_per_leg) for seed in args.wide_seeds]
    for seed, hip_range, count in sources:
        which = "" if seed == args.seed and hip_range == "standard" else f" {hip_range} seed {seed}"
        description = f"labelling{which} (exact FEC)"
        data = load_or_generate(evaluator, cache_path(args.data, set_prefix("train", hip_range), seed, count), seed,
                                count, description, hip_range=hip_range)  # fmt: skip
        parts.append(split(data, args.val_fraction, seed, not args.no_mirror, args.canonical_legs))
        sets.append(data)
    statistics = (sets[0] if len(sets) == 1 else VfaDataset.concatenate(sets)).statistics()
    if len(parts) == 1:
        return parts[0][0], parts[0][1], statistics
    return (VfaDataset.concatenate([t for t, _ in parts]), VfaDataset.concatenate([v for _, v in parts]),
            statistics)  # fmt: skip


def initial_net(args: argparse.Namespace, config: NetConfig) -> tuple[VfaNet | VfaUNet, NetConfig]:
    """A fresh network of ``config``, or with ``--init-weights`` the saved one (its architecture and layer
    sizes replace ``config``'s; the encoding must be the same, else the inputs would mean something else)."""
    if args.init_weights is None:
        return build_net(config), config
    net = load_model(args.init_weights)
    if net.config.encoding != config.encoding:
        raise SystemExit(f"--init-weights {args.init_weights}: encoding {net.config.encoding} differs from this "
                         f"run's {config.encoding}")  # fmt: skip
    if net.config.safe_head != config.safe_head:
        raise SystemExit(f"--init-weights {args.init_weights}: safe head {net.config.safe_head}, --safe-weight "
                         f"{args.safe_weight} asks for {config.safe_head}")  # fmt: skip
    LOG.info("starting from %s (%s)", args.init_weights, net.config.architecture)
    # The data's frame decides (``--canonical-legs``): trained weights of either kind are a starting point.
    net.config = replace(net.config, canonical_legs=config.canonical_legs)
    net.train()
    return net, net.config


def optimum_target(
    label: torch.Tensor, safe_mask: torch.Tensor, distance_sq: torch.Tensor, args: argparse.Namespace
) -> torch.Tensor:
    """Cross-entropy target: the exact optimum (class indices), or with ``--soft-target`` M a distribution
    (1 - M) one-hot + M softmax over the safe cells of -(d^2 - d_opt^2) / T (peaks at the optimum's distance)."""
    if args.soft_target <= 0.0:
        return label
    logits = (distance_sq[label][:, None] - distance_sq[None, :]) / args.soft_cells2
    soft = torch.softmax(logits.masked_fill(safe_mask < 0.5, float("-inf")), dim=1)
    one_hot = nn.functional.one_hot(label, distance_sq.numel()).float()
    return (1.0 - args.soft_target) * one_hot + args.soft_target * soft


def lr_schedule(
    optimiser: torch.optim.Optimizer, total_steps: int, warmup_steps: int
) -> torch.optim.lr_scheduler.LambdaLR:
    """Learning-rate factor per step: linear warm-up from 0 over ``warmup_steps``, then a cosine decay to 0
    at ``total_steps`` (without warm-up: ``CosineAnnealingLR`` with T_max = total_steps)."""

    def factor(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / warmup_steps
        progress = min((step - warmup_steps) / max(total_steps - warmup_steps, 1), 1.0)
        return 0.5 * (1.0 + math.cos(math.pi * progress))

    return torch.optim.lr_scheduler.LambdaLR(optimiser, factor)


def evaluate(net: VfaNet | VfaUNet, batches: Batches, batch_size: int = 1024,
             decode_settings: VfaDecode | None = None) -> dict[str, float]:
    """Perfect-match rate, safe rate and mean distance to the exact optimum [m] on ``batches`` of the optimum
    head's argmax; with ``decode_settings`` also the perfect-match and safe rates of that decode
    (``decoded_perfect_match``, ``decoded_safe``)."""
    net.eval()
    n = batches.data.cells
    res = batches.encoding.resolution_m
    match = safe = decoded_match = decoded_safe = 0
    distance = 0.0
    with torch.inference_mode():
        for start in range(0, len(batches), batch_size):
            index = np.arange(start, min(start + batch_size, len(batches)))
            image, scalars, label, safe_mask = batches.tensors(index)
            if decode_settings is None:
                logits, safe_logits = net.optimum_logits(image, scalars), None
            else:
                logits, safe_logits = net(image, scalars)
            choice = logits.argmax(dim=1)
            match += int((choice == label).sum())
            safe += int(safe_mask.gather(1, choice[:, None]).sum())
            d_row = (choice // n - label // n).float()
            d_col = (choice % n - label % n).float()
            distance += float(torch.sqrt(d_row**2 + d_col**2).sum()) * res
            if decode_settings is not None:
                probability = None if safe_logits is None else torch.sigmoid(safe_logits).numpy()
                unknown = image[:, 1].reshape(len(index), -1).numpy() > 0.5
                decoded = torch.from_numpy(decode(decode_settings, logits.numpy(), probability, unknown))
                decoded_match += int((decoded == label).sum())
                decoded_safe += int(safe_mask.gather(1, decoded[:, None]).sum())
    count = max(len(batches), 1)
    metrics = {"perfect_match": match / count, "safe": safe / count, "mean_distance_m": distance / count}
    if decode_settings is not None:
        metrics.update(decoded_perfect_match=decoded_match / count, decoded_safe=decoded_safe / count)
    return metrics


def selection_settings(args: argparse.Namespace) -> VfaDecode | None:
    """The decode that ``--select-on`` scores epochs with (None: the argmax, scored by ``evaluate`` anyway)."""
    return VfaDecode(mode="combined", safe_weight=args.select_safe_weight) if args.select_on == "combined" else None


def selection_score(metrics: dict[str, float], args: argparse.Namespace) -> float:
    """The validation figure epochs are compared by: the argmax's perfect match, or the combined decode's
    perfect match + safe rate (tune_vfa_decode's rule; the decode the shipped weights run)."""
    if args.select_on == "combined":
        return metrics["decoded_perfect_match"] + metrics["decoded_safe"]
    return metrics["perfect_match"]


def train(args: argparse.Namespace) -> dict[str, object]:
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    started = time.perf_counter()
    model = RobotModel.from_name(args.robot)
    evaluator = FootholdEvaluator(model)
    s = evaluator.settings
    train_set, val_set, statistics = training_sets(args, evaluator)
    labelling_s = time.perf_counter() - started
    LOG.info("dataset: %d samples, %.1f %% adapted, %d without a safe candidate (left out)",
             statistics["samples"], 100 * statistics["adapted_fraction"], statistics["no_safe"])  # fmt: skip
    encoding = EncodingConfig(cells=s.patch_cells, resolution_m=s.resolution_m,
                              nominal_hip_height_m=round(float(model.nominal_base_height_m), 4))  # fmt: skip
    config = NetConfig(tuple(args.channels), args.hidden, args.safe_weight > 0.0, encoding, args.architecture,
                       tuple(args.decoder_channels), args.roughness_features, args.head_blocks,
                       args.canonical_legs)  # fmt: skip
    net, config = initial_net(args, config)
    net = net.to(memory_format=torch.channels_last)
    train_batches, val_batches = Batches(train_set, encoding), Batches(val_set, encoding)
    # A fixed training subset as large as the validation set, scored like it each epoch (over-fitting check).
    train_probe = Batches(train_batches.data.subset(np.arange(min(len(val_batches), len(train_batches)))), encoding)
    parameters = sum(p.numel() for p in net.parameters())
    LOG.info("training on %d samples, validating on %d (mirrored: %s, canonical legs: %s); %d parameters",
             len(train_batches), len(val_batches), not args.no_mirror and not args.canonical_legs,
             args.canonical_legs, parameters)  # fmt: skip
    optimiser = torch.optim.Adam(net.parameters(), lr=args.lr)
    steps_per_epoch = math.ceil(len(train_batches) / args.batch_size)
    schedule = lr_schedule(optimiser, args.epochs * steps_per_epoch, round(args.warmup * steps_per_epoch))
    n = encoding.cells
    r, c = np.meshgrid(np.arange(n) - n // 2, np.arange(n) - n // 2, indexing="ij")
    distance_sq = torch.from_numpy((r**2 + c**2).reshape(-1).astype(np.float32))  # [cells^2] from the nominal
    rng = np.random.default_rng([args.seed, 11])
    history: list[dict[str, float]] = []
    selecting = selection_settings(args)
    best: dict[str, float] | None = None
    best_state: dict[str, torch.Tensor] | None = None
    training_started = time.perf_counter()
    if args.init_weights is not None:  # epoch 0: the starting weights, kept unless an epoch beats them
        best = {"epoch": 0, "loss": None, "lr_end": None, **evaluate(net, val_batches, decode_settings=selecting),
                "train_perfect_match": evaluate(net, train_probe)["perfect_match"],
                "elapsed_s": time.perf_counter() - training_started}  # fmt: skip
        best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
        history.append(best)
        LOG.info("epoch 0 (the initial weights): validation perfect match %.1f %%, safe %.1f %%, mean distance "
                 "%.4f m; training-subset perfect match %.1f %%", 100 * best["perfect_match"], 100 * best["safe"],
                 best["mean_distance_m"], 100 * best["train_perfect_match"])  # fmt: skip
    for epoch in range(1, args.epochs + 1):
        net.train()
        order = rng.permutation(len(train_batches))
        total = 0.0
        bar = tqdm(range(steps_per_epoch), desc=f"epoch {epoch}/{args.epochs}", unit="batch", leave=False)
        for step in bar:
            index = np.sort(order[step * args.batch_size : (step + 1) * args.batch_size])
            image, scalars, label, safe_mask = train_batches.tensors(index)
            optimum, safe_logits = net(image, scalars)
            loss = nn.functional.cross_entropy(optimum, optimum_target(label, safe_mask, distance_sq, args))
            if safe_logits is not None:
                loss = loss + args.safe_weight * nn.functional.binary_cross_entropy_with_logits(safe_logits, safe_mask)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            schedule.step()
            total += loss.item()
            bar.set_postfix(loss=f"{total / (step + 1):.3f}")
        metrics = {"epoch": epoch, "loss": total / steps_per_epoch, "lr_end": schedule.get_last_lr()[0],
                   **evaluate(net, val_batches, decode_settings=selecting),
                   "train_perfect_match": evaluate(net, train_probe)["perfect_match"],
                   "elapsed_s": time.perf_counter() - training_started}  # fmt: skip
        history.append(metrics)
        LOG.info("epoch %d (%.0f s): loss %.3f, validation perfect match %.1f %%, safe %.1f %%, mean distance "
                 "%.4f m; training-subset perfect match %.1f %%", epoch, metrics["elapsed_s"], metrics["loss"],
                 100 * metrics["perfect_match"], 100 * metrics["safe"], metrics["mean_distance_m"],
                 100 * metrics["train_perfect_match"])  # fmt: skip
        if selecting is not None:
            LOG.info("epoch %d: combined decode (λ %g) perfect match %.1f %%, safe %.1f %%", epoch,
                     selecting.safe_weight, 100 * metrics["decoded_perfect_match"], 100 * metrics["decoded_safe"])
        if best is None or selection_score(metrics, args) > selection_score(best, args):
            best = metrics
            best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
            save_model(net, args.out / "vfa_cnn.pt", {"seed": args.seed, "best_epoch": epoch, "partial": True})
        elif args.patience and epoch - int(best["epoch"]) >= args.patience:
            LOG.info("early stop: no better validation score (--select-on %s) since epoch %d", args.select_on,
                     best["epoch"])
            break
        # this epoch's duration (after epoch 0's scoring when fine-tuning)
        epoch_s = metrics["elapsed_s"] - (history[-2]["elapsed_s"] if len(history) > 1 else 0.0)
        if args.max_training_s and epoch < args.epochs and metrics["elapsed_s"] + epoch_s > args.max_training_s:
            LOG.info("time budget: epoch %d would end after %.0f s; stopping", epoch + 1, args.max_training_s)
            break
    assert best is not None and best_state is not None
    net.load_state_dict(best_state)
    training_s = time.perf_counter() - training_started
    report = {
        "command": "python -m tal_lab.vital.train_vfa " + " ".join(sys.argv[1:]),
        "seed": args.seed,
        "extra_seeds": args.extra_seeds,
        "init_weights": None if args.init_weights is None else str(args.init_weights),
        "samples_per_leg": args.samples_per_leg,
        "sampling": mix_description(),
        "wide_seeds": args.wide_seeds,
        "wide_samples_per_leg": args.wide_samples_per_leg if args.wide_seeds else None,
        "wide_sampling": mix_description("wide") if args.wide_seeds else None,
        "dataset": statistics,
        "train_samples": len(train_batches),
        "validation_samples": len(val_batches),
        "mirrored": not args.no_mirror and not args.canonical_legs,
        "canonical_legs": args.canonical_legs,
        "net": {
            "architecture": config.architecture,
            "decoder_channels": list(config.decoder_channels) if config.architecture == "unet" else None,
            "roughness_features": config.roughness_features,
            "head_blocks": config.head_blocks,
            "canonical_legs": config.canonical_legs,
            "channels": list(config.channels),
            "hidden": config.hidden,
            "safe_head": config.safe_head,
            "parameters": parameters,
        },
        "optimiser": {
            "name": "Adam",
            "lr": args.lr,
            "schedule": f"linear warm-up {args.warmup:g} epochs, then cosine to 0 at epoch {args.epochs}",
            "epochs": args.epochs,
            "epochs_run": sum(1 for h in history if h["epoch"] > 0),
            "patience": args.patience,
            "max_training_s": args.max_training_s,
            "batch_size": args.batch_size,
            "safe_weight": args.safe_weight,
            "soft_target": args.soft_target,
            "soft_cells2": args.soft_cells2,
            "select_on": args.select_on,
            "select_safe_weight": args.select_safe_weight if args.select_on == "combined" else None,
        },
        "best_epoch": best,
        "history": history,
        "labelling_or_cache_s": labelling_s,
        "training_s": training_s,
        "threads": args.threads,
        "machine": {
            "cpu": platform.processor() or platform.machine(),
            "python": platform.python_version(),
            "torch": torch.__version__,
        },
    }
    args.out.mkdir(parents=True, exist_ok=True)
    validation = {k: best[k] for k in ("perfect_match", "safe", "mean_distance_m")}
    metadata = {
        "seed": args.seed,
        "extra_seeds": args.extra_seeds,
        "wide_seeds": args.wide_seeds,
        "best_epoch": best["epoch"],
        "validation": validation,
    }
    save_model(net, args.out / "vfa_cnn.pt", metadata)
    (args.out / "vfa_cnn_training.json").write_text(json.dumps(report, indent=1))
    LOG.info("saved %s (%.2f MB); training took %.0f s", args.out / "vfa_cnn.pt",
             (args.out / "vfa_cnn.pt").stat().st_size / 1e6, training_s)  # fmt: skip
    return report


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="[train_vfa] %(message)s")
    train(parse_args(argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
