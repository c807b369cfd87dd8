"""Vehicle parameters: the YAML schema, physical plausibility checks, derived terms.

The model is built from physical quantities (masses, inertias, geometry,
tyre data), never from printed matrix entries, so another vehicle is another
YAML file. `VehicleParameters` also offers the composite terms of Sharp's
equations (mass-matrix entries, gyroscopic coefficients) under the names the
papers use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

from ptw_rt.schema import ConfigError, Number, Section, Text, read_yaml, validate

POSITIVE_MASS = Number("kg", gt=0, le=2000)
INERTIA = Number("kg m^2", ge=1e-4, le=1e4)
LENGTH = Number("m", gt=0, lt=5)
# a tyre of 1e-300 N/rad designed, and every ride ran DEGRADED with nothing said: engineering ranges
STIFFNESS = Number("N/rad", ge=10, le=1e6)

VEHICLE_SCHEMA = Section(
    {
        "name": Text(),
        "gravity": Number("m/s^2", gt=9.7, lt=9.9),
        "front_frame": Section(
            {
                "mass": POSITIVE_MASS,
                "cg_forward": Number("m", ge=-3, le=3),
                "cg_height": LENGTH,
                "cg_ahead_of_steer_axis": Number("m", ge=-0.5, le=0.5),
                "inertia_x": INERTIA,
                "inertia_z": INERTIA,
            }
        ),
        "rear_frame": Section(
            {
                "mass": POSITIVE_MASS,
                "cg_height": LENGTH,
                "inertia_x": INERTIA,
                "inertia_z": INERTIA,
                "inertia_xz": Number("kg m^2"),
            }
        ),
        "steering": Section(
            {
                "caster_deg": Number("deg", ge=0, lt=60),
                "trail": Number("m", ge=0, lt=0.5),
                "damping": Number("N m s/rad", ge=0, le=1000),
            }
        ),
        "front_wheel": Section({"spin_inertia": INERTIA, "radius": Number("m", gt=0.05, lt=1.0)}),
        "rear_wheel": Section({"spin_inertia": INERTIA, "radius": Number("m", gt=0.05, lt=1.0)}),
        "front_vertical_load": Number("N", gt=0, le=20000),
        "front_contact_forward": LENGTH,
        "rear_contact_behind": LENGTH,
        "front_tyre": Section(
            {
                "cornering_stiffness": STIFFNESS,
                "camber_stiffness": STIFFNESS,
                "relaxation_length": Number("m", gt=0, lt=2),
            }
        ),
        "rear_tyre": Section(
            {
                "cornering_stiffness": STIFFNESS,
                "camber_stiffness": STIFFNESS,
                "relaxation_length": Number("m", gt=0, lt=2),
            }
        ),
    },
    # the rider and luggage this scooter carries beyond the rider rear_frame.mass includes (negative: lighter):
    # the learned tyres' N/rad rest on the mass, which no sensor sees (docs/estimator.md, "The payload")
    optional={"added_mass": (Number("kg", ge=-150, le=300), 0.0)},
)
# the rear frame keeps at least this share of its mass when a negative added mass takes some away
MIN_REAR_FRAME_SHARE = 0.2


@dataclass(frozen=True)
class VehicleParameters:
    """Physical parameters of Sharp's two-body lateral model (SI units)."""

    name: str
    g: float
    m_f: float  # front frame mass
    k: float  # front frame CoM ahead of reference point
    j: float  # front frame CoM height
    e: float  # front frame CoM ahead of steering axis
    i_fx: float
    i_fz: float
    m_r: float
    h: float
    i_rx: float
    i_rz: float
    c_rxz: float
    caster: float  # rad
    trail: float
    damping: float
    i_fy: float
    r_f: float
    i_ry: float
    r_r: float
    front_load: float
    l_f: float
    l_r: float
    c_af: float
    c_gf: float
    sigma_f: float
    c_ar: float
    c_gr: float
    sigma_r: float

    # ----- composite terms, as named in the papers -------------------------
    @property
    def mass(self) -> float:
        return self.m_f + self.m_r

    @property
    def rear_load(self) -> float:
        """Static normal load on the rear tyre [N]: the weight less the front's."""
        return self.mass * self.g - self.front_load

    @property
    def mfk(self) -> float:
        return self.m_f * self.k

    @property
    def roll_moment(self) -> float:
        """M_f j + M_r h: first moment of mass about the ground line."""
        return self.m_f * self.j + self.m_r * self.h

    @property
    def mfe(self) -> float:
        return self.m_f * self.e

    @property
    def gyro_front(self) -> float:
        """i_fy / R_f: front wheel spin angular momentum per unit forward speed."""
        return self.i_fy / self.r_f

    @property
    def gyro_total(self) -> float:
        return self.i_fy / self.r_f + self.i_ry / self.r_r

    @property
    def steer_stiffness(self) -> float:
        """M_f e g - eta Z_f (Z_f negative, z down): the gravity/trail steer moment."""
        return self.mfe * self.g + self.trail * self.front_load

    def mass_matrix_terms(self) -> dict[str, float]:
        s, c = math.sin(self.caster), math.cos(self.caster)
        m_f, k, j, e = self.m_f, self.k, self.j, self.e
        return {
            "e33": self.mass,
            "e34": self.mfk,
            "e35": self.roll_moment,
            "e36": self.mfe,
            "e44": m_f * k**2 + self.i_rz + self.i_fx * s**2 + self.i_fz * c**2,
            "e45": m_f * j * k - self.c_rxz + (self.i_fz - self.i_fx) * s * c,
            "e46": m_f * e * k + self.i_fz * c,
            "e55": m_f * j**2 + self.m_r * self.h**2 + self.i_rx + self.i_fx * c**2 + self.i_fz * s**2,
            "e56": m_f * e * j + self.i_fz * s,
            "e66": self.i_fz + m_f * e**2,
        }

    def nominal_stiffness(self) -> tuple[float, float, float, float]:
        """(C_af, C_gf, C_ar, C_gr): the order of seed 001's parameter vector Theta."""
        return (self.c_af, self.c_gf, self.c_ar, self.c_gr)

    def with_added_mass(self, dm: float) -> VehicleParameters:
        """The vehicle with a point mass dm [kg] at the rear-frame CoM (a heavier or, dm < 0, lighter rider, or
        luggage): the model's reference point is that CoM, so the inertias about it stay, and the front tyre takes
        its lever-rule share of the weight. What the simulator's `added_mass` and the file's `added_mass` both do.
        ValueError (the reason, for the caller's message) if it leaves the rear frame less than MIN_REAR_FRAME_SHARE
        of its mass."""
        if self.m_r + dm <= MIN_REAR_FRAME_SHARE * self.m_r:
            raise ValueError(f"{dm:g} kg leaves too little of rear_frame.mass ({self.m_r:g} kg)")
        front_share = self.l_r / (self.l_f + self.l_r)
        return replace(self, m_r=self.m_r + dm, front_load=self.front_load + dm * self.g * front_share)

    def scaled(
        self,
        mass_inertia: float = 1.0,
        stiffness: float = 1.0,
        front_stiffness: float = 1.0,
        rear_stiffness: float = 1.0,
    ) -> VehicleParameters:
        """A perturbed vehicle: masses and inertias (and load) times one factor, tyre stiffness times another, and
        each axle's two stiffnesses times its own factor besides (tyres that differ by axle)."""
        mi = mass_inertia
        return replace(
            self,
            m_f=self.m_f * mi,
            m_r=self.m_r * mi,
            i_fx=self.i_fx * mi,
            i_fz=self.i_fz * mi,
            i_rx=self.i_rx * mi,
            i_rz=self.i_rz * mi,
            c_rxz=self.c_rxz * mi,
            front_load=self.front_load * mi,
            c_af=self.c_af * stiffness * front_stiffness,
            c_gf=self.c_gf * stiffness * front_stiffness,
            c_ar=self.c_ar * stiffness * rear_stiffness,
            c_gr=self.c_gr * stiffness * rear_stiffness,
        )

    def as_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def vehicle_from_mapping(raw: Any, source: str = "<vehicle>", prefix: str = "vehicle") -> VehicleParameters:
    v = validate(raw, VEHICLE_SCHEMA, source, prefix)
    ff, rf, st = v["front_frame"], v["rear_frame"], v["steering"]
    params = VehicleParameters(
        name=v["name"],
        g=v["gravity"],
        m_f=ff["mass"],
        k=ff["cg_forward"],
        j=ff["cg_height"],
        e=ff["cg_ahead_of_steer_axis"],
        i_fx=ff["inertia_x"],
        i_fz=ff["inertia_z"],
        m_r=rf["mass"],
        h=rf["cg_height"],
        i_rx=rf["inertia_x"],
        i_rz=rf["inertia_z"],
        c_rxz=rf["inertia_xz"],
        caster=math.radians(st["caster_deg"]),
        trail=st["trail"],
        damping=st["damping"],
        i_fy=v["front_wheel"]["spin_inertia"],
        r_f=v["front_wheel"]["radius"],
        i_ry=v["rear_wheel"]["spin_inertia"],
        r_r=v["rear_wheel"]["radius"],
        front_load=v["front_vertical_load"],
        l_f=v["front_contact_forward"],
        l_r=v["rear_contact_behind"],
        c_af=v["front_tyre"]["cornering_stiffness"],
        c_gf=v["front_tyre"]["camber_stiffness"],
        sigma_f=v["front_tyre"]["relaxation_length"],
        c_ar=v["rear_tyre"]["cornering_stiffness"],
        c_gr=v["rear_tyre"]["camber_stiffness"],
        sigma_r=v["rear_tyre"]["relaxation_length"],
    )
    if v["added_mass"]:
        try:
            params = params.with_added_mass(v["added_mass"])
        except ValueError as exc:
            raise ConfigError(f"{source}: {prefix}.added_mass: {exc}") from None
    check_physical(params, f"{source}: {prefix}")
    return params


def check_physical(p: VehicleParameters, source: str) -> None:
    """Reject values that pass the per-key bounds but describe no real vehicle."""
    weight = p.mass * p.g
    if p.front_load >= weight:
        raise ConfigError(
            f"{source}.front_vertical_load: {p.front_load:.1f} N is more than the whole vehicle's weight "
            f"({weight:.1f} N)"
        )
    terms = p.mass_matrix_terms()
    m4 = [
        [terms["e33"], terms["e34"], terms["e35"], terms["e36"]],
        [terms["e34"], terms["e44"], terms["e45"], terms["e46"]],
        [terms["e35"], terms["e45"], terms["e55"], terms["e56"]],
        [terms["e36"], terms["e46"], terms["e56"], terms["e66"]],
    ]
    import numpy as np

    if np.min(np.linalg.eigvalsh(np.array(m4))) <= 0:
        raise ConfigError(
            f"{source}: the mass matrix built from front_frame/rear_frame masses, inertias and CoM positions "
            "is not positive definite; check inertia_x, inertia_z, inertia_xz and cg_* values"
        )
    if abs(p.c_rxz) >= math.sqrt(p.i_rx * p.i_rz):
        raise ConfigError(
            f"{source}.rear_frame.inertia_xz: |{p.c_rxz}| must be smaller than sqrt(inertia_x * inertia_z) "
            "for a physical inertia tensor"
        )


def load_vehicle(path: str | Path) -> VehicleParameters:
    doc = read_yaml(path)
    if not isinstance(doc, dict) or "vehicle" not in doc:
        raise ConfigError(f"{path}: missing top-level 'vehicle' section")
    return vehicle_from_mapping(doc["vehicle"], str(path))
