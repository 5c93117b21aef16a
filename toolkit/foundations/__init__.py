"""Foundations: what every layer above stands on, importing nothing else of the toolkit.

- :mod:`.conventions`  frames, poses, Grood-Suntay joint coordinates, left/right mirroring;
- :mod:`.errors`       the two error families: bad input and numerical failure;
- :mod:`.geometry`     sphere and plane fits, rigid registration, principal axes;
- :mod:`.surfaces`     signed distances, occupancy and nearest points on closed meshes;
- :mod:`.imaging`      surfaces and 3D Slicer markups as they come from imaging (units, SPACE);
- :mod:`.motion_io`    motion tables (CSV);
- :mod:`.recording`    Rerun helpers (recordings, meshes, transforms, blueprints).
"""
