"""From imaging to mechanism parameters (frames, alignment, sphere fits, isometric fibres, bounded
optimisation). The pipeline is not built yet: this package holds nothing but this docstring, and the
command line does not offer ``knee fit``."""
