"""Numba options shared by the compiled inner loops.

``NO_REFCOUNT`` compiles a function without Numba's runtime (NRT), so
without reference counting. The loops pass the plant's constants as one
namedtuple (:data:`app.engine.physics.plant.Kernel`) that holds twelve
tables as arrays; every time the tuple entered an inlined helper, Numba
incremented and later decremented each array's count with an atomic
operation, and its pruning pass cannot remove pairs split across branches
(numba/numba#2350, where its authors show the same remedy). In the gap
diagnosis's log replay those calls were 68 % of the time (sampled with gdb and
perf), and without them a replay of the protocol's logs took 5.4 instead of
36 ms, to the same bits (``tests/test_physics_properties.py`` compares the
two builds).

The price is that such a function cannot allocate: an ``np.empty`` in it,
or in any compiled function it calls (Numba compiles those without the
runtime too), fails to compile with a typing error, so scratch arrays are
made by the caller and passed in. Views and slices of arrays passed in are
fine: the caller holds them alive for the call. Functions that allocate keep
the runtime and may call these freely (the simulator's closed loop does: its
controllers allocate their fuzzy inference's scratch per tick).

``_nrt`` is the option's name in Numba's CPU target (since 2015; 0.68 here). Its
leading underscore means that Numba does not document it. A Numba that
dropped it would refuse it at the first compile ("Unrecognized options"), so
the simulator and every test would stop loudly rather than slow down
unseen.
"""

from __future__ import annotations

from typing import Any, Final

NO_REFCOUNT: Final[dict[str, Any]] = {"_nrt": False}
"""``njit`` keyword arguments for a compiled function that never allocates."""
