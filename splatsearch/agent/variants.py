"""The agent's variants (no heavy imports: the command-line parser reads them)."""

#: the thesis' Table IV rows: the full system and its four ablations (the evaluation runs all five)
VARIANTS = ("splatsearch", "no_nvsm", "no_inpaint", "nearest_frontier", "gaussnav")
