"""kgnavbench: target-driven visual navigation in the 30 iTHOR kitchens (README.md, DESIGN.md).

Importing the package registers its Gymnasium ids (kgnavbench/vecenv.py): `kgnavbench/FloorPlan1-v0`
.. `kgnavbench/FloorPlan30-v0`, `kgnavbench/train-v0`, `kgnavbench/val-v0`, `kgnavbench/test-v0`.
"""

from .vecenv import register_ids as _register_ids

_register_ids()
