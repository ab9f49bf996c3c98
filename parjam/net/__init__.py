"""The packing as a network: the periodic box and the particles (:mod:`.system`), the pair
potential of Eq. (1)'s setting (:mod:`.potential`) and the d x d contact blocks of Eq. (1)
(:mod:`.blocks`), the spatial domain decomposition that every stage runs on (:mod:`.domain`),
the serial contact network with its rattlers, z and dz (:mod:`.network`), the one distributed
active network that every analysis builds on (:mod:`.active`), reproducible sums over ranks
(:mod:`.exactsum`), and structural observables of the network: hexatic order (:mod:`.order`)
and contact-number fluctuations (:mod:`.fluctuations`).
"""
