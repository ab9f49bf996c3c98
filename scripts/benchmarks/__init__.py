"""parjam's benchmarks: each module measures one stage of the pipeline by its command, next to
its physical limit and a numpy/scipy peer, in one run (README.md in this folder).

Run them with ``scripts/bench NAME [--quick] [--old REV] [--doc PAGE]``; ``scripts/bench list``
names them.
"""

NAMES = ("pack", "modes", "kpm", "softmodes", "moduli", "memory")
