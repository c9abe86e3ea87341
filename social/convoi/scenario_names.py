"""Scenario names and the held-out seeds (no heavy imports: the command-line parser reads them)."""

SCENARIOS = ("hallway", "blind_corner", "static_groups", "dynamic_groups", "doorway", "crossing")
#: OLiVia-Nav's four (thesis Table I order)
THESIS_SCENARIOS = SCENARIOS[:4]
#: the held-out seeds of OLiVia-Nav's Table I (training uses seeds below 100). Ten, not five: per
#: seed one method's Hausdorff distance spans 0.03-0.48 m in dynamic_groups, and on five seeds
#: OLiVia-Nav and DWA differed there by 1 mm, which is noise.
TABLE_ONE_SEEDS = tuple(range(1000, 1010))
#: the held-out doorway (Table II): the seeds the LLU buffer is filled on and the test seeds; no
#: training scene ever uses them (training doors come from DOOR_TRAIN_SEEDS with sampled widths)
LLU_ADAPT_SEEDS = tuple(range(500, 520))
LLU_TEST_SEEDS = TABLE_ONE_SEEDS
DOOR_TRAIN_SEEDS = tuple(range(200, 206))
