"""The error a kernel's parameter dataclass raises for a value it refuses."""

from __future__ import annotations


class InvalidParameter(ValueError):
    """A parameter value that is not allowed; ``name`` is the offending parameter.

    The pipeline's stage parameters raise the same class (``pipeline.params.ParamError``), so
    a planner's refusal reaches the user under the option's name without parsing messages.
    """

    def __init__(self, name: str, message: str):
        super().__init__(message)
        self.name = name
        self.message = message
