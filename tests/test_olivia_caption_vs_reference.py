"""benchmarks/olivia_caption_vs_reference.py: the agreement summary."""

import math
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))

import olivia_caption_vs_reference as cr  # noqa: E402


def test_agreement_counts_per_reference_action():
    rows = [{"caption": "keep_right", "reference": "keep_right"}, {"caption": "keep_left", "reference": "keep_right"},
            {"caption": "straight", "reference": "straight"}, {"caption": "turn_left", "reference": "keep_right"}]
    s = cr.agreement(rows)
    assert s["states"] == 4 and s["agree"] == 0.5
    assert s["per_reference_action"] == {"keep_right": {"n": 3, "agree": 1 / 3}, "straight": {"n": 1, "agree": 1.0}}
    assert math.isnan(cr.agreement([])["agree"])
