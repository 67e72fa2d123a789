"""Run inside Blender: how Blender itself sees an EXR (its type, and the view layer and passes its compositor's
Image node offers). Prints JSON. Usage: python read_layout.py FILE.exr"""

import json
import sys

import bpy

path = sys.argv[sys.argv.index("--") + 1] if "--" in sys.argv else sys.argv[1]
image = bpy.data.images.load(path)
scene = bpy.context.scene
tree = bpy.data.node_groups.new("probe", "CompositorNodeTree")
node = tree.nodes.new("CompositorNodeImage")
node.image = image
print(
    "LAYOUT "
    + json.dumps({"type": image.type, "layer": node.layer, "passes": [o.name for o in node.outputs if o.enabled]})
)
