"""``railtraj-sim``: generate a synthetic tunnel survey and its truth from the command line.

    railtraj-sim SCENARIO OUT_DIR [--seed N] [--size F] [--overwrite]
    railtraj-sim --list
"""

from __future__ import annotations

import argparse
import sys
import time

from railtraj.errors import RailtrajError
from railtraj.sim.scenarios import CATALOGUE, DEMO


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="railtraj-sim",
        description="Generate a synthetic multi-run tunnel survey (SPEC.md layout) in OUT_DIR/survey "
                    "and its ground truth in OUT_DIR/truth.")
    p.add_argument("scenario", nargs="?", help=f"scenario name ({', '.join(CATALOGUE)}); see --list")
    p.add_argument("out_dir", nargs="?", help="folder to write survey/ and truth/ into")
    p.add_argument("--seed", type=int, default=0, help="random seed of noise and drift (default 0)")
    p.add_argument("--size", type=float, default=1.0,
                   help="scale of lengths and point density (default 1.0; 0.1-0.2 for quick tests)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing survey/ and truth/")
    p.add_argument("--list", action="store_true", help="list the scenarios and exit")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status (0 success, 1 error, 2 usage)."""
    parser = _parser()
    args = parser.parse_args(argv)
    if args.list:
        for name, scn in CATALOGUE.items():
            tag = " (demo)" if name == DEMO else ""
            print(f"{name}{tag}: {scn.description}")
        return 0
    if not args.scenario or not args.out_dir:
        parser.print_usage(sys.stderr)
        print("railtraj-sim: error: give SCENARIO and OUT_DIR (or --list)", file=sys.stderr)
        return 2
    from railtraj.sim.simulate import generate  # heavy imports (Open3D) only when needed

    start = time.perf_counter()
    try:
        result = generate(args.scenario, args.out_dir, seed=args.seed, size=args.size,
                          overwrite=args.overwrite, progress=lambda m: print(m, flush=True))
    except RailtrajError as err:
        print(f"railtraj-sim: error: {err}", file=sys.stderr)
        return 1
    for line in result.summary():
        print(line)
    print(f"done in {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":   # pragma: no cover
    sys.exit(main())
