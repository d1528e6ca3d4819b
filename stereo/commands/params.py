"""`emcstereo params`: the parameter table of the eight variants, counted from the code."""

from __future__ import annotations

import argparse
import itertools

from stereo.model import EMCStereo


def variant_name(ema: bool, msf: bool, coord: bool) -> str:
    """The paper's name of a variant: 'none', 'EMA', 'EMA+MSF', …, 'all'."""
    parts = [name for name, on in (("EMA", ema), ("MSF", msf), ("Coord", coord)) if on]
    if len(parts) == 3:
        return "all"
    return "+".join(parts) or "none"


def parameter_table(max_disp: int = 192) -> list[tuple[str, int, int, int]]:
    """(variant, parameters, trainable, state_dict tensors) for each of the eight variants."""
    rows = []
    for ema, msf, coord in itertools.product((False, True), repeat=3):
        model = EMCStereo(ema=ema, msf=msf, coord=coord, max_disp=max_disp)
        total = sum(p.numel() for p in model.parameters())
        trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
        rows.append((variant_name(ema, msf, coord), total, trainable, len(model.state_dict())))
    return rows


def _run(args: argparse.Namespace) -> int:
    print(f"{'variant':<10} {'parameters':>12} {'trainable':>12} {'tensors':>8}")
    for name, total, trainable, tensors in parameter_table(args.max_disp):
        print(f"{name:<10} {total:>12,} {trainable:>12,} {tensors:>8}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add `params` to the `emcstereo` command."""
    parser = sub.add_parser("params", help="print the parameter count of the eight variants")
    parser.add_argument("--max-disp", type=int, default=192, help="disparity range (default 192)")
    parser.set_defaults(func=_run)
