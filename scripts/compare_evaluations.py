"""Two rows of ``sarah-eval`` runs on the same windows, compared window by window: each figure's
difference and ratio with 95 % paired intervals (``sarah_models.evaluation.comparison``), where
the rows' own intervals overlap.

    python scripts/compare_evaluations.py after/ before/                  # the "model" rows
    python scripts/compare_evaluations.py ema/:model raw/:model --out ema-vs-raw.md
    python scripts/compare_evaluations.py run/:vae run/:random

Each EVAL is a sarah-eval --out folder, optionally :KEY (a row's key in its table1.json:
model, vae, random, nn, real, ...; default: the model row, or the folder's only row beside GT,
as in a --methods vae run). Both folders must list the same windows in their windows.json and
have scored them with the same --batch-clips.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from sarah_data.atomic import atomic_write_text
from sarah_models.evaluation.comparison import ComparisonError, compare, comparison_markdown
from sarah_models.evaluation.tables import MethodResult, read_table1_row


def read_evaluation(spec: str) -> tuple[MethodResult, list]:
    """``FOLDER[:KEY]`` -> (that row, the folder's window listing; without KEY the model row or
    the only other scored one); ValueError naming the file and the problem."""
    folder, sep, key = spec.rpartition(":")
    if not sep or "/" in key or not folder:
        folder, key = spec, None
    listing = Path(folder) / "windows.json"
    try:
        windows = json.loads(listing.read_text())["windows"]
    except (OSError, ValueError, KeyError) as exc:
        raise ValueError(f"{listing}: not a sarah-eval windows.json ({exc})") from None
    return read_table1_row(Path(folder) / "table1.json", key), windows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("a", metavar="EVAL_A", help="FOLDER[:KEY], the row read as A")
    parser.add_argument("b", metavar="EVAL_B", help="FOLDER[:KEY], the row A is compared with")
    parser.add_argument("--out", type=Path, default=None, help="also write the table here (.md)")
    args = parser.parse_args(argv)
    try:
        (row_a, windows_a), (row_b, windows_b) = read_evaluation(args.a), read_evaluation(args.b)
        if windows_a != windows_b:
            raise ValueError(f"{args.a} and {args.b} evaluated different windows (their "
                             "windows.json differ): score both on the same shards and --windows")
        differences = compare(row_a.table, row_b.table)
    except (ValueError, ComparisonError) as exc:
        print(f"compare_evaluations.py: error: {exc}", file=sys.stderr)
        return 2
    text = (f"A = {row_a.label} ({args.a}), B = {row_b.label} ({args.b}); {row_a.table.num_clips} "
            f"windows, paired 95 % intervals (Avg and per-window figures: bootstrap; pooled: "
            f"jackknife); values as Table 1 shows them.\n\n"
            + comparison_markdown(differences, row_a.table, "A", "B"))
    print(text, end="")
    if args.out is not None:
        atomic_write_text(args.out, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
