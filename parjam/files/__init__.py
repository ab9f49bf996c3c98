"""parjam's files, and no physics: H5MD packing files (:mod:`.h5md`), row-block reads and writes
that no rank holds whole (:mod:`.rowio`), the output policy (:mod:`.outputs`), the input policy
(:mod:`.inputs`), the files PETSc's options name (:mod:`.petscfiles`), the manifest of a
``pack`` directory (:mod:`.manifest`), checkpoints inside a member (:mod:`.checkpoint`, its
files :mod:`.checkpointio`), configurations made elsewhere (:mod:`.importer`), and one module
per result kind: spectra (:mod:`.modes_io`), soft modes (:mod:`.softmodes`), moduli
(:mod:`.moduli`), lengths (:mod:`.lengths`), a scene stage's member (:mod:`.stagefile`).
"""
