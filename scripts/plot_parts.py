"""FGD_acc by body part of rows from several ``sarah-eval`` runs in one figure: the by-part bars
``sarah-eval`` draws for one evaluation (plots/fgd_acc_by_part.png), for rows of different
evaluations of the same windows (a model beside Random, the real floor and its VAE, say).

    python scripts/plot_parts.py parts.png floors/table1.json:real floors/table1.json:random \
        pick/table1.json:model="the pick" w256/table1.json:model="256-wide flow"

Each ROW is TABLE1_JSON:KEY, optionally =LABEL (the row's own label otherwise); rows must have
been scored by part and on the same windows (the figure says so only through its source files).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sarah_models.evaluation.tables import MethodResult, plot_parts, read_table1_row


def read_row(spec: str) -> MethodResult:
    """``TABLE1_JSON:KEY[=LABEL]`` -> that row; ValueError naming the file and the problem."""
    source, _, label = spec.partition("=")
    path, sep, key = source.rpartition(":")
    if not sep or not path or not key:
        raise ValueError(f"{spec}: want TABLE1_JSON:KEY[=LABEL]")
    row = read_table1_row(path, key)
    if not row.table.shell_parts:
        raise ValueError(f"{path}: row {key!r} was not scored by body part (an older sarah-eval, "
                         "or the GT row)")
    return row if not label else MethodResult(row.key, label, row.causal, row.fps, row.table,
                                              row.gaze, row.reference)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path, help="the PNG to write")
    parser.add_argument("rows", nargs="+", metavar="ROW", help="TABLE1_JSON:KEY[=LABEL]")
    args = parser.parse_args(argv)
    try:
        rows = [read_row(spec) for spec in args.rows]
    except ValueError as exc:
        print(f"plot_parts.py: error: {exc}", file=sys.stderr)
        return 2
    if any(row.table.shell_parts != rows[0].table.shell_parts for row in rows):
        print("plot_parts.py: error: the rows split the shell differently (other windows or "
              "shards); score them on the same windows", file=sys.stderr)
        return 2
    print(plot_parts(args.out, rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
