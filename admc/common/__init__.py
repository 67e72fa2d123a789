"""What training and evaluation share, defined once: metrics, the tone map, the data layout.

The bottom layer of admc, next to `admc.errors`: it imports no other admc module, so `stores/`,
`model/` and `pipeline/` can all use it (imports flow cli -> pipeline -> model -> stores -> common).
"""
