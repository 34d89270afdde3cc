"""``segsnake evaluate PRED TRUTH [--json]``: compare a mask with a truth mask.

Prints Dice, Jaccard, volumes and surface distances in mm (definitions in
:mod:`segsnake.metrics`). The two masks must be on the same grid (shape and affine).
With ``--json`` the output is one JSON object; infinite distances (one mask empty) are ``null``.
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

from segsnake.metrics import METRIC_KEYS, evaluate_masks, load_mask_pair

HELP = "compare a mask with a truth mask (Dice, Jaccard, volumes, surface distances in mm)"

_LABELS = {
    "dice": ("Dice", ""),
    "jaccard": ("Jaccard", ""),
    "volume_pred_mm3": ("volume (pred)", "mm^3"),
    "volume_truth_mm3": ("volume (truth)", "mm^3"),
    "volume_difference_mm3": ("volume difference", "mm^3"),
    "volume_difference_rel": ("relative volume difference", ""),
    "hausdorff95_mm": ("Hausdorff 95 %", "mm"),
    "assd_mm": ("average symmetric surface distance", "mm"),
    "hausdorff_mm": ("Hausdorff (max)", "mm"),
}


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("evaluate", help=HELP, description=HELP)
    parser.add_argument("pred", metavar="PRED", help="predicted mask (NIfTI, non-zero = inside)")
    parser.add_argument("truth", metavar="TRUTH", help="truth mask on the same grid")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.set_defaults(func=run)
    return parser


def _json_value(v: float) -> Any:
    return v if math.isfinite(v) else None


def format_table(metrics: dict[str, float]) -> str:
    """Aligned ``name  value unit`` lines for the terminal."""
    width = max(len(_LABELS[k][0]) for k in METRIC_KEYS)
    lines = []
    for key in METRIC_KEYS:
        label, unit = _LABELS[key]
        v = metrics[key]
        if key in ("dice", "jaccard", "volume_difference_rel"):
            text = f"{v:.4f}" if math.isfinite(v) else str(v)
        else:
            text = f"{v:.2f}" if math.isfinite(v) else str(v)
        lines.append(f"{label:<{width}}  {text}{' ' + unit if unit else ''}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    pred, truth, spacing = load_mask_pair(args.pred, args.truth)
    metrics = evaluate_masks(pred, truth, spacing)
    if args.json:
        record = {"pred": str(args.pred), "truth": str(args.truth), "spacing": list(spacing)}
        record.update({k: _json_value(metrics[k]) for k in METRIC_KEYS})
        print(json.dumps(record, allow_nan=False))
    else:
        print(format_table(metrics))
    return 0
