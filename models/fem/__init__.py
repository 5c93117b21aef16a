"""The "association" finite-element model (seed 000), one small module per component, as in SOFA:

- :mod:`.material`  isotropic linear elasticity (Lamé constants, the 6x6 elasticity matrix);
- :mod:`.elements`  co-rotational linear hexahedra and tetrahedra: stiffness, rotations, forces;
- :mod:`.assembly`  a fixed-sparsity global matrix filled without Python loops.

Built so far: the element force fields and their assembly, verified against mechanics references
(tests/test_fem_elements.py). The grid, mapping, collision, springs, integrator and scene are to come.
"""
