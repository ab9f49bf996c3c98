"""Making jammed packings (``parjam pack``): the random and file starts, the minimisers (FIRE on
the slab engine, Newton with the exact Hessian), the O'Hern bisection to phi_c, the dphi ladder
and target pressures, and the stability check of every returned state.  Everything here runs on
the spatial domain decomposition of :mod:`parjam.net` and returns results: writing them is
:mod:`parjam.study.members`' (through :mod:`parjam.files`).

- :mod:`.protocol` -- the protocol's settings (``PackingProtocol``), shared with scenes.
- :mod:`.packing` -- the Jammer: bisection, ladder, pressures of one configuration.
- :mod:`.ensemble` -- the states of one ensemble member and the flags that say when a state is
  not what it seems.
- :mod:`.engine`, :mod:`.kernels` (+ ``_kernels.c``), :mod:`.cellsearch`, :mod:`.rowops`,
  :mod:`.fire`, :mod:`.forces`, :mod:`.minimize` -- the slab engine, the compiled pair kernel,
  the neighbour searches by cells, the row operations of a rebuild and of the ghosts'
  exchange, FIRE and Newton.
- :mod:`.randomstart`, :mod:`.filestart` -- where a configuration starts (a file's rows are
  read by :mod:`parjam.files.rowio`).
- :mod:`.stability`, :mod:`.jamnet` -- the stable-minimum check and the per-state network.
- :mod:`.staterows` -- a state as each rank's rows, and the rows of its file.
"""
