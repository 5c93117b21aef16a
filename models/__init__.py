"""Models: the physics of the knee. Imports only :mod:`knee.foundations`.

- :mod:`.mechanism`  the 1-DoF spatial parallel mechanism (parameters, closure equations, solver);
- :mod:`.phantom`    procedural bone and skin geometry of a parameter set (the bundled demo subject);
- :mod:`.fem`        the association finite-element model (grid, elements, fields, integrator, the
  virtual depth camera, the model of a knee, the methods that deform it toward a point cloud);
- :mod:`.prior`      the mechanism as a kinematic prior for depth data (flexion estimate, tibia correction);
- :mod:`.evaluation` target point errors (ACL/PCL footprints, epiphysis);
- :mod:`.statics`, :mod:`.contact`, :mod:`.gait`, :mod:`.osteotomy`  the clinical questions (seed 001).
"""
