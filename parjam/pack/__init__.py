"""Making jammed packings (``parjam pack``): the random and file starts, the minimisers (FIRE on
the slab engine, Newton with the exact Hessian), the O'Hern bisection to phi_c, the dphi ladder
and target pressures, the stability check of every returned state, and checkpoints inside a
member.  Everything here runs on the spatial domain decomposition of :mod:`parjam.net`.

- :mod:`.protocol` -- the protocol's settings (``PackingProtocol``), shared with scenes.
- :mod:`.packing` -- the Jammer: bisection, ladder, pressures of one configuration.
- :mod:`.ensemble` -- the states of one ensemble member and their flags.
- :mod:`.engine`, :mod:`.kernels` (+ ``_kernels.c``), :mod:`.fire`, :mod:`.forces`,
  :mod:`.minimize` -- the slab engine, the compiled pair kernel, FIRE and Newton.
- :mod:`.randomstart`, :mod:`.filestart` -- where a configuration starts.
- :mod:`.stability`, :mod:`.jamnet` -- the stable-minimum check and the per-state network.
- :mod:`.staterows`, :mod:`.checkpoint` -- a state as each rank's rows; checkpoints.
"""
