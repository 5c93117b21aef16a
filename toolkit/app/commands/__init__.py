"""One module per ``knee`` command, each with ``run(args) -> int`` (dispatched by :mod:`knee.app.cli`)."""
