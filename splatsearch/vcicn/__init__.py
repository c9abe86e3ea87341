"""VCICN: the view-completion network of the NVSM (thesis Section 4.2.4), trained on simulator
ground truth.

* :mod:`splatsearch.vcicn.data`: training pairs (local-map renders of the hemisphere views and
  the simulator's ray-cast ground truth of the same cameras), one ``.npz`` shard per house.
* :mod:`splatsearch.search.completion`: the flax multi-view U-Net and :class:`VCICNInpainter`.
* :mod:`splatsearch.vcicn.train`: optax training with checkpoints, early stopping and a wall-time
  budget; :mod:`splatsearch.vcicn.weights`: the shipped weights and their checksum.

See docs/vcicn.md.
"""
