"""Shared vocabulary: cameras, light rig, face rig, environment maps, image I/O and colour.

World frame: metres, right-handed, +y up, +z out of the face (the cameras stand on the
+z side looking at the head), +x to the subject's left (the viewer's right).
"""
