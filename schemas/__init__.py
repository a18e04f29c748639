"""Installed as ``swanky_schemas``: the wire protocol, config JSON Schemas and bundled .msg files.

Data only; find files with ``importlib.resources.files("swanky_schemas")``.
"""
