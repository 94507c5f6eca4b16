"""`gear view`: the trained twin in a browser (viser), with a slider per joint.

scene.py turns a `gear.twin.Twin` into per-part geometry and per-joint poses (no viser);
server.py puts that geometry into a viser scene and wires the sliders to it.
"""
