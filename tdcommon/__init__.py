"""The bottom layer: data types with their wire encodings, rigid transforms, meshes and the robot model.

Every other package of the project may import it; it imports nothing of ours.
"""
