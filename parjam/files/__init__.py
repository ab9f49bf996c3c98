"""parjam's files, and no physics: H5MD packing files (:mod:`.h5md`), row-block reads and writes
that no rank holds whole (:mod:`.rowio`), the output policy (:mod:`.outputs`), the input policy
(:mod:`.inputs`), the files PETSc's options name (:mod:`.petscfiles`), the manifest of a
``pack`` directory (:mod:`.manifest`), checkpoint files (:mod:`.checkpointio`), spectrum files
(:mod:`.modes_io`), and configurations made elsewhere (:mod:`.importer`).
"""
