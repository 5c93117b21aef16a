"""Reports and plots of the commands: the fit, the FEM comparison, the osteotomy."""
