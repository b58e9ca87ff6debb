"""The built-in presets, installed as the package ``leap_core.projects`` (pyproject.toml's package-dir).

This file makes the folder a package, so that an editable install maps the name onto this folder and a
regular install ships it; ``leap_core.schema.projects_dir`` finds it through ``importlib.resources``.
"""
