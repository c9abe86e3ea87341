"""Trained weights shipped with the package (package data, read with :mod:`importlib.resources`).

``vcicn.npz``: the VCICN view-completion network (:mod:`splatsearch.search.completion`);
``vcicn.json``: its provenance (training data seeds, command, commit, validation metrics) and the
SHA-256 that the loader checks.
"""
