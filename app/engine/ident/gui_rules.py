"""The thesis GUIs' input rules and button logic (Figures 3.19, 3.27; Appendices 1–2).

Both identification GUIs take their inputs in a fixed order: a field unlocks
only once the one before it holds a valid value, a valid field turns green
(and locks), an invalid one keeps the user there with the GUI's own message,
and "Clear" resets everything. The messages below are the Appendix code's,
word for word, so a lab moving from the MATLAB tool sees the same prompts.

SPEC §6 adds one rule the linear GUI's code lacks (its N fields only refuse
zero): N_s and N_d must be at least 30 on both rigs.

Units are the GUI's: degrees, mm and mm² (the Appendix 2 field is
"CylinderStrokemm"), bar absolute.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

from app.engine.params import ParameterError

# Appendix 1/2 messages, verbatim.
MSG_ROM = "Please enter a reasonable value! It should be between 0-360 degrees."
MSG_REASONABLE = "Please enter a reasonable value!"
MSG_N = "Value cannot be lower than 30, login new value!"
MSG_PW = "Working pressure can be min. 1 bar and max. 8 bar!"
MSG_CORRECT = "Please enter correct value!"
MSG_ROTARY_START = "Please enter the required parameters! Start with range of motion (ROM)."
MSG_ROTARY_READY = "Parameters has been defined successfully, please connect to proceed."
MSG_LINEAR_START = "Please enter the input parameters on the left!"
MSG_LINEAR_READY = "Parameters are entered successfully, system is ready for connection."
MSG_CONNECTED = "Connection is successfull, Press Start button to continue!"
MSG_STARTED = "Experiments are started, please wait to complete!"
MSG_ENDED = "Experiment process is ended and system is disconnected!"
MSG_DISCONNECTED = "System is disconnected!"


MIN_TESTS = 30  # Appendix 1/2: "suggested as >=30" experiments per kind


def _positive(v: float) -> bool:
    return math.isfinite(v) and v > 0.0


def _count(v: float) -> bool:
    return math.isfinite(v) and v >= MIN_TESTS and float(v).is_integer()


@dataclass(frozen=True)
class FieldRule:
    """One GUI input box.

    Attributes:
        name: Field key.
        label: What the GUI shows, with the unit.
        check: Validity test of the value alone.
        error: Message when invalid.
        prompt: Message once the field is valid (what to enter next).
    """

    name: str
    label: str
    check: Callable[[float], bool]
    error: str
    prompt: str


ROTARY_FIELDS: tuple[FieldRule, ...] = (
    FieldRule("rom_deg", "Range of motion ROM [deg]", lambda v: math.isfinite(v) and 0.0 < v <= 360.0, MSG_ROM,
              "Enter the vane area of the actuator"),
    FieldRule("vane_area_mm2", "Vane area A_v [mm²]", _positive, MSG_REASONABLE,
              "Enter the torque radius of the actuator"),
    FieldRule("radius_mm", "Torque radius r [mm]", _positive, MSG_REASONABLE,
              "Specify the number of static experiments [suggested as >=30]"),
    FieldRule("ns", "# of tests for static exp. N_s", _count, MSG_N,
              "Specify the number of dynamic experiments [suggested as >=30]"),
    FieldRule("nd", "# of tests for dynamic exp. N_d", _count, MSG_N,
              "Specify the working pressure [cannot be lower than 1]"),
    FieldRule("pw_bar", "Absolute working pressure P_w [bar]", lambda v: math.isfinite(v) and 1.0 <= v <= 8.0,
              MSG_PW, MSG_ROTARY_READY),
)

LINEAR_FIELDS: tuple[FieldRule, ...] = (
    FieldRule("stroke_mm", "Cylinder stroke L [mm]", _positive, MSG_CORRECT, "Enter piston diameter"),
    FieldRule("piston_diameter_mm", "Piston diameter PD [mm]", _positive, MSG_CORRECT, "Enter rod diameter"),
    FieldRule("rod_diameter_mm", "Rod diameter RD [mm]", _positive, MSG_CORRECT, "Enter number of static experiments"),
    FieldRule("ns", "# of static experiments N_s", _count, MSG_N, "Enter number of dynamic experiments"),
    FieldRule("nd", "# of dynamic experiments N_d", _count, MSG_N, MSG_LINEAR_READY),
)


def suggested_values(rig: Literal["rotary", "linear"], cylinder: Literal["C1", "C2", "C3"] = "C3") -> dict[str, float]:
    """What each field of a form suggests before anything is typed.

    The rotary form suggests the forearm robot's DRVS-32-270 (thesis 3.2.1: ROM, A_v = H·W, r = (D2 + H)/2)
    and the linear form the catalogue geometry of ``cylinder`` (thesis Tables 4.5–4.6's cylinders): a
    suggestion for a 300 mm C3 left on a 225 mm C1 would send its static tests past the end of the stroke
    and scale every force by the wrong piston area. Both suggest the GUIs' minimum of 30 tests per kind
    and the rotary one the thesis's working pressure (3 bar abs, :class:`RotaryInputs`).

    Args:
        rig: Which form.
        cylinder: The linear rig's cylinder (ignored by the rotary form).

    Returns:
        Field name → suggested value, in the fields' units.
    """
    from app.engine.params import LinearCylinder, VaneCylinder

    if rig == "rotary":
        v = VaneCylinder()
        return {"rom_deg": v.rom_deg, "vane_area_mm2": round(v.vane_area * 1e6, 6),
                "radius_mm": round(v.radius * 1e3, 6), "ns": MIN_TESTS, "nd": MIN_TESTS,
                "pw_bar": RotaryInputs().pw_bar}
    c = LinearCylinder.catalogue(cylinder)
    return {"stroke_mm": round(c.stroke * 1e3, 6), "piston_diameter_mm": round(c.bore * 1e3, 6),
            "rod_diameter_mm": round(c.rod * 1e3, 6), "ns": MIN_TESTS, "nd": MIN_TESTS}


def _check_fields(obj: object, rules: tuple[FieldRule, ...]) -> None:
    """Raise the GUI's message for the first invalid field of ``obj``."""
    for rule in rules:
        if not rule.check(float(getattr(obj, rule.name))):
            raise ParameterError(f"{rule.name}: {rule.error}")


@dataclass(frozen=True)
class RotaryInputs:
    """Validated inputs of the rotary friction identification (Figure 3.19).

    Attributes:
        rom_deg: Range of motion [deg], 0 < ROM ≤ 360.
        vane_area_mm2: Vane area A_v [mm²] (> 0).
        radius_mm: Torque radius r [mm] (> 0).
        ns: Static experiments per direction (≥ 30).
        nd: Dynamic experiments per direction (≥ 30).
        pw_bar: Working pressure P_w [bar abs], 1–8.
    """

    rom_deg: float = 270.0
    vane_area_mm2: float = 855.0
    radius_mm: float = 23.0
    ns: int = 100
    nd: int = 100
    pw_bar: float = 3.0

    def __post_init__(self) -> None:
        _check_fields(self, ROTARY_FIELDS)

    @property
    def torque_per_bar(self) -> float:
        """A_v·r [N·m/bar] (Eq 3.4 with pressures in bar)."""
        return self.vane_area_mm2 * 1e-6 * self.radius_mm * 1e-3 * 1e5


@dataclass(frozen=True)
class LinearInputs:
    """Validated inputs of the linear friction identification (Figure 3.27).

    Attributes:
        stroke_mm: Stroke L [mm] (> 0).
        piston_diameter_mm: PD [mm] (> 0).
        rod_diameter_mm: RD [mm], 0 < RD < PD.
        ns: Static experiments per direction (≥ 30).
        nd: Dynamic experiments per direction (≥ 30).
    """

    stroke_mm: float = 300.0
    piston_diameter_mm: float = 32.0
    rod_diameter_mm: float = 12.0
    ns: int = 100
    nd: int = 100

    def __post_init__(self) -> None:
        _check_fields(self, LINEAR_FIELDS)
        if not self.rod_diameter_mm < self.piston_diameter_mm:
            raise ParameterError(f"rod_diameter_mm: {MSG_CORRECT}")

    @property
    def area_a(self) -> float:
        """Cap-side area [m²]."""
        return math.pi * (self.piston_diameter_mm * 1e-3) ** 2 / 4.0

    @property
    def area_rod(self) -> float:
        """Rod area [m²]."""
        return math.pi * (self.rod_diameter_mm * 1e-3) ** 2 / 4.0


@dataclass
class FieldResult:
    """Outcome of entering one value.

    Attributes:
        ok: Whether the value was accepted.
        message: The GUI's message box text after this entry.
        editable: The field that is open for input now (``None`` when all done).
    """

    ok: bool
    message: str
    editable: str | None


ButtonName = Literal["connect", "disconnect", "start", "stop", "estimate", "clear"]


@dataclass
class GuidedForm:
    """A thesis GUI: ordered fields plus its Connect/Start/Stop/Estimate/Clear logic.

    ``enter`` accepts a value only for the field that is currently open; a
    valid value turns the field green (``valid[name]``) and opens the next.
    The buttons follow Appendix 1's enable flags: Connect once every field
    is valid; Start after Connect; Stop while running; Estimate only after
    the experiments finished; Clear whenever nothing runs.

    Args:
        rig: ``"rotary"`` or ``"linear"``.
    """

    rig: Literal["rotary", "linear"] = "rotary"
    values: dict[str, float] = field(default_factory=dict)
    valid: dict[str, bool] = field(default_factory=dict)
    message: str = ""
    phase: Literal["editing", "ready", "connected", "running", "finished", "estimated"] = "editing"

    def __post_init__(self) -> None:
        self.clear()

    @property
    def rules(self) -> tuple[FieldRule, ...]:
        """The field sequence of this rig."""
        return ROTARY_FIELDS if self.rig == "rotary" else LINEAR_FIELDS

    @property
    def editable(self) -> str | None:
        """The field open for input, or ``None`` once all are valid."""
        if self.phase != "editing":
            return None
        for r in self.rules:
            if not self.valid.get(r.name):
                return r.name
        return None

    def enter(self, name: str, value: float) -> FieldResult:
        """Type ``value`` into field ``name``; nothing changes when refused."""
        rules = {r.name: r for r in self.rules}
        if name not in rules:
            raise ParameterError(f"unknown field {name!r}; fields: {', '.join(rules)}")
        if name != self.editable:
            opened = self.editable
            why = f"fill in {opened} first" if opened else "clear the parameters first"
            return FieldResult(False, f"{rules[name].label} is locked: {why}.", opened)
        rule = rules[name]
        v = float(value)
        ok = rule.check(v)
        if ok and name == "rod_diameter_mm" and not v < self.values.get("piston_diameter_mm", math.inf):
            ok = False
        if not ok:
            self.message = rule.error
            return FieldResult(False, rule.error, name)
        self.values[name] = v
        self.valid[name] = True
        self.message = rule.prompt
        if self.editable is None:
            self.phase = "ready"
        return FieldResult(True, rule.prompt, self.editable)

    def inputs(self) -> RotaryInputs | LinearInputs:
        """The validated inputs (only once every field is valid)."""
        if self.phase == "editing":
            raise ParameterError(f"inputs incomplete: {self.editable} is next")
        v = self.values
        if self.rig == "rotary":
            return RotaryInputs(v["rom_deg"], v["vane_area_mm2"], v["radius_mm"], int(v["ns"]), int(v["nd"]),
                                v["pw_bar"])
        return LinearInputs(v["stroke_mm"], v["piston_diameter_mm"], v["rod_diameter_mm"], int(v["ns"]), int(v["nd"]))

    def buttons(self) -> dict[ButtonName, bool]:
        """Which buttons are enabled now."""
        p = self.phase
        return {
            "connect": p == "ready", "disconnect": p == "connected", "start": p == "connected",
            "stop": p == "running", "estimate": p == "finished", "clear": p in ("editing", "ready", "finished",
                                                                                    "estimated"),
        }

    def press(self, button: ButtonName) -> str:
        """Press a button; refused (``ParameterError``, nothing changes) when disabled."""
        if not self.buttons().get(button, False):
            raise ParameterError(f"the {button!r} button is disabled while {self.phase}")
        nxt = {"connect": ("connected", MSG_CONNECTED), "disconnect": ("ready", MSG_DISCONNECTED),
               "start": ("running", MSG_STARTED), "stop": ("finished", MSG_ENDED),
               "estimate": ("estimated", self.message)}
        if button == "clear":
            self.clear()
        else:
            self.phase, self.message = nxt[button]  # type: ignore[assignment]
        return self.message

    def finish(self) -> None:
        """The experiments completed on their own (Estimate becomes active)."""
        if self.phase == "running":
            self.phase, self.message = "finished", MSG_ENDED

    def clear(self) -> None:
        """The "Clear" button: every field empty and open from the first."""
        self.values = {}
        self.valid = {}
        self.phase = "editing"
        self.message = MSG_ROTARY_START if self.rig == "rotary" else MSG_LINEAR_START
