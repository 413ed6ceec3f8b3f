"""Methods: what `train --method NAME` fits, each one module behind one interface (`Method`), found by name in one
registry (`model.methods.registry`): `density` (the default), `nerf`, and whatever a plugin registers.

    method = method_named("density")          # model.methods.registry
    register(MyMethod())                      # a test's or a notebook's own; plugins: the entry-point group
    run = load_trained(run_dir)               # model.run: the method its config.json names opens the run

docs/DESIGN.md ("Methods") says how to add one.
"""

from nerfpipe.model.methods.base import Method, Prepared, RunFiles, TrainContext, TrainModel
from nerfpipe.model.methods.hooks import Batch, Hook, LoopState
from nerfpipe.model.methods.registry import (
    DEFAULT,
    method_named,
    method_names,
    method_of_checkpoint,
    method_of_run,
    methods,
    register,
    unregister,
)

__all__ = [
    "DEFAULT",
    "Batch",
    "Hook",
    "LoopState",
    "Method",
    "Prepared",
    "RunFiles",
    "TrainContext",
    "TrainModel",
    "method_named",
    "method_names",
    "method_of_checkpoint",
    "method_of_run",
    "methods",
    "register",
    "unregister",
]
