"""The robot model (URDF) -> Rerun, in four modules, each importing only those before it:

* ``parse.py``: the URDF text -> yourdfpy's model, what of a malformed description can be kept;
* ``kinematics.py``: the joint table (one tree per root, mimic joints) and joint motion (joint
  values -> parent-child transforms), shared with joints.py and the demo robot;
* ``meshes.py``: each visual's geometry (boxes, cylinders, spheres, mesh files found through the
  resolver and loaded by trimesh) as one Rerun archetype;
* ``description.py``: the converter of /robot_description and ``--urdf PATH`` (its ``SPEC``).

Nothing is imported here: joints.py imports kinematics.py, and description.py imports joints.py.
"""
