"""admc.model.inference: whole images through trained generators (tiles, exposure, ensemble, OIDN base).

Imports nets and the shared model modules, never training."""
