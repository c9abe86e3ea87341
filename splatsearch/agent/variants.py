"""The agent's variants (no heavy imports: the command-line parser reads them).

``splatsearch`` is the full system: NVSM views completed by the VCICN (the shipped weights; OpenCV
inpainting when the installation ships none, see ``AgentConfig.inpainter``). Its ablations, as in
the thesis' Table IV: ``no_nvsm`` (raw camera crops only), ``no_vcicn`` (NVSM, raw renders, no
completion; ``no_inpaint`` is the same variant under its earlier name), ``opencv_inpaint`` (NVSM
with OpenCV inpainting instead of the VCICN), ``nearest_frontier`` and ``gaussnav``.
"""

#: the full system and its ablations (the evaluation runs all of them by default)
VARIANTS = ("splatsearch", "no_nvsm", "no_vcicn", "opencv_inpaint", "nearest_frontier", "gaussnav")

#: earlier names still accepted, mapped to the variant they mean
VARIANT_ALIASES = {"no_inpaint": "no_vcicn"}


def canonical_variant(name: str) -> str:
    """``name`` with an alias replaced by its variant; raises ValueError for an unknown name."""
    v = VARIANT_ALIASES.get(name, name)
    if v not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS} (or an alias: "
                         f"{', '.join(f'{a}={b}' for a, b in VARIANT_ALIASES.items())}), got {name!r}")
    return v
