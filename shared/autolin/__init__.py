"""autolin: automatic linearization (thesis chapter 3).

Record a function once by operator overloading, generate its linearization, forward,
reverse and accumulation programs, simplify them to scalar multiply/add programs and run
them batched with numpy. Quaternions carry rotation-vector gradients. See docs/autolin.md.
"""

from .ops import GRAD, OPS, SIZE, Op, register
from .programs import Linearized, NonFiniteError, compile, counters, generate
from .trace import (
           Mat3,
           Quat,
           Rot3,
           Scalar,
           TracingError,
           Vec3,
           angle_axis,
           call,
           cos,
           cross,
           dot,
           sin,
           sqrt,
           to_matrix,
           trace,
)

__all__ = ["GRAD", "OPS", "SIZE", "Linearized", "Mat3", "NonFiniteError", "Op", "Quat", "Rot3", "Scalar",
           "TracingError", "Vec3", "angle_axis", "call", "compile", "cos", "counters", "cross", "dot", "generate",
           "register", "sin", "sqrt", "to_matrix", "trace"]
