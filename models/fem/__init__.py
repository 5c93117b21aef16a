"""The "association" finite-element model (seed 000), one small module per component, as in SOFA:

- :mod:`.material`  isotropic linear elasticity (Lamé constants, the 6x6 elasticity matrix);
- :mod:`.elements`  co-rotational linear hexahedra and tetrahedra: stiffness, rotations, forces;
- :mod:`.assembly`  a fixed-sparsity global matrix filled without Python loops.

- :mod:`.meshing`   structured boxes of hexahedra and their tetrahedral split;
- :mod:`.geometry`  signed distances / occupancy against closed meshes (open3d);
- :mod:`.grid`      the sparse soft-tissue grid around the skin (inside / boundary / outside cells);
- :mod:`.mapping`   trilinear embedding of bone nodes and skin vertices in the grid (J, J^T);
- :mod:`.bones`     bone surfaces filled with tetrahedra (400-700 per bone);
- :mod:`.fields`    force fields on the grid: soft tissue, mapped bones, springs, penalty contact;
- :mod:`.integrator` implicit Euler, matrix-free preconditioned CG;
- :mod:`.scene`     the association model of a phantom knee.

Status: elements, assembly, grid, mapping and bone meshing are verified by tests. The integrator and
scene run but are work in progress: not yet at the speed target (about 0.4 s per step on the default
model instead of 1/30 s) and the paper's bone-force magnitudes do not transfer to these units.
"""
