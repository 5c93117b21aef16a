"""Foundations of the knee toolkit: conventions, errors, file I/O, Rerun recording, the ``knee`` CLI.

Nothing in ``toolkit`` imports ``models`` or ``fitting`` (dependencies point one way:
``fitting -> models -> toolkit``), except the command line, which is the top of the stack.
"""

__all__ = ["conventions", "errors"]
