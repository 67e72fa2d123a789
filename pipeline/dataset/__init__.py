"""The dataset: renders tiled into the Zarr patch store (`tile`), and its summary (`report`)."""
