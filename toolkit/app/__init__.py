"""The application layer: what sits on top of the library and nothing below imports.

- :mod:`.cli` and :mod:`.commands` the ``knee`` command line, one module per command;
- :mod:`.console`     output-path checks, argument parsing, the progress bar;
- :mod:`.launch`      the installed ``knee`` script's entry point; :mod:`.threads` the BLAS threads it sets by
  the machine's load first;
- :mod:`.demo`        the FEM half of ``knee demo``;
- :mod:`.experiments` experiment runners: the standard cases and the comparison of the FEM methods;
- :mod:`.reports`     reports and plots (fit, comparison, osteotomy);
- :mod:`.views`       Rerun recordings (sweep, FEM run, gait).
"""
