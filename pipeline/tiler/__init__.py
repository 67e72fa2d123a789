"""The tiler: renders cut into rows of the Zarr patch store (`tile`), and the store's summary (`report`); the
`dataset` and `tile` commands run it (stages/dataset.py)."""
