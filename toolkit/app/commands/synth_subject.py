"""``knee synth-subject OUT_DIR``: a complete synthetic subject folder from a parameter set."""

from __future__ import annotations

from pathlib import Path

from knee.app.console import say
from knee.fitting.synthetic import make_subject


def run(args) -> int:
    out = Path(args.out_dir)
    say(f"knee synth-subject: writing a synthetic subject from '{args.model}' (seed {args.seed}) ...")
    make_subject(out, model=args.model, seed=args.seed, frames=args.frames)
    print(f"subject folder: {out}")
    print(f"fit it with:    knee fit {out} --out {out}-fit")
    return 0
