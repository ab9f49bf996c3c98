"""Studies described by scene files (``parjam run``), one module per concept:

- :mod:`parjam.study.members`: one ensemble member of a packing study, from its start to its
  files (``parjam pack`` and the pack stages of ``parjam run``);
- :mod:`parjam.study.scene`: the scene model and its validation (TOML -> :class:`Scene`);
- :mod:`parjam.study.plan`: the stages a scene needs, their keys, solvers and estimates;
- :mod:`parjam.study.records`: the per-state work of an analysis stage (calls the physics);
- :mod:`parjam.study.runner`: the stages member by member over groups of ranks, resumable;
- :mod:`parjam.study.summary`: the summary file format, written by the runner and read by the
  plots (parjam.plot.paper, parjam.plot.spectra);
- :mod:`parjam.study.fits`: power-law fits with bootstrap errors over the members.
"""
