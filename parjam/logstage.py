"""PETSc log stages: phases of the work as they appear in ``-log_view``."""

from parjam import env


class log_stage:
    """A PETSc log stage (shown by -log_view) around a phase of the work."""

    _stages = {}

    def __init__(self, name):
        PETSc = env.petsc()
        if name not in self._stages:
            self._stages[name] = PETSc.Log.Stage(name)
        self.stage = self._stages[name]

    def __enter__(self):
        self.stage.push()

    def __exit__(self, *exc):
        self.stage.pop()
        return False
