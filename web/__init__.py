"""The web UI, installed as the package ``app.web`` (pyproject.toml's package-dir).

This file makes the folder a package, so that an editable install maps the name onto this folder and a
regular install ships it; ``app.main`` serves it from where ``importlib.resources`` finds it.
"""
