"""The "association" finite-element model (seed 000), one small module per component, as in SOFA:

- :mod:`.material`  isotropic linear elasticity (Lamé constants, the 6x6 elasticity matrix);
- :mod:`.elements`  co-rotational linear hexahedra and tetrahedra: stiffness, rotations, forces;
- :mod:`.assembly`  a fixed-sparsity global matrix filled without Python loops.

- :mod:`.meshing`   structured boxes of hexahedra and their tetrahedral split;
- :mod:`.grid`      the sparse soft-tissue grid around the skin (inside / boundary / outside cells);
- :mod:`.mapping`   trilinear embedding of bone nodes and skin vertices in the grid (J, J^T);
- :mod:`.bones`     bone surfaces filled with tetrahedra (400-700 per bone);
- :mod:`.fields`    force fields on the grid: soft tissue, mapped bones, springs, penalty contact;
- :mod:`.integrator` implicit Euler, matrix-free preconditioned CG; :mod:`.system` the matrix's kept
  pattern; :mod:`.factor` its Cholesky factorisation (CHOLMOD, or SuperLU);
- :mod:`.scene`     the association model of a phantom knee;
- :mod:`.depth`     the virtual RGB-D camera and its noise (real depth images and point clouds:
  :mod:`knee.foundations.pointclouds`);
- :mod:`.forces`    the paper's bone forces and the surface forces toward the depth points;
- :mod:`.methods`   the methods on a point cloud: the paper's, and the mechanism as the kinematic prior.

Speed (BENCHMARKS.md): 15-20 implicit steps per second on the default model, short of the 30 asked.
"""
