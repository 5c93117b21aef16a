"""The knee models: the 1-DoF spatial parallel mechanism (``models.mechanism``) and the procedural
phantom geometry (``models.phantom``). The FEM association model, contact mechanics and the gait chain
join here as they are built."""
