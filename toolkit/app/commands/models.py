"""``knee models``: the bundled parameter sets, one line each."""

from __future__ import annotations

from knee.models.mechanism.params import bundled_models, load_model


def run(args) -> int:
    for name, desc in bundled_models().items():
        p = load_model(name)
        kinds = "/".join(sorted(set(p.kinds)))
        print(f"{name:22s} {'TF+PF' if p.has_pf else 'TF   '}  {kinds:22s} {desc}")
    return 0
