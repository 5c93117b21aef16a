"""``knee synth-subject OUT_DIR``: a complete synthetic subject folder from a parameter set."""

from __future__ import annotations

from knee.app.console import out_dir, say
from knee.fitting.synthetic import MAX_FRAMES, MIN_FRAMES, make_subject
from knee.foundations.errors import KneeInputError
from knee.foundations.files import staged_folder


def run(args) -> int:
    out = out_dir(args.out_dir, force=False, flag="OUT_DIR")
    if not MIN_FRAMES <= args.frames <= MAX_FRAMES:
        raise KneeInputError(f"--frames must be {MIN_FRAMES}-{MAX_FRAMES}, got {args.frames}")
    say(f"knee synth-subject: writing a synthetic subject from '{args.model}' (seed {args.seed}) ...")
    with staged_folder(out) as tmp:
        make_subject(tmp, model=args.model, seed=args.seed, frames=args.frames)
    print(f"subject folder: {out}")
    print(f"fit it with:    knee fit {out} --out {out}-fit")
    return 0
