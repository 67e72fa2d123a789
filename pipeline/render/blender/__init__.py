"""Blender Cycles as a renderer of the corpus: `.blend` scenes rendered by Blender in a process of its own.

bpy (Blender as a Python module) pins NumPy below 2 and admc's stack needs NumPy 2, so the two cannot
share an environment: Blender runs as a separate interpreter (`locate.py` finds it), executing
`worker.py`, which imports nothing of admc. The worker writes Blender's passes to a multilayer EXR;
`passes.py` turns them into admc's buffers here.
"""
