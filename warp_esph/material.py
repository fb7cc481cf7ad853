"""Material parameters and named presets.

Units are SI: Lamé parameters, yield stress and hardening in Pa, flow rate in 1/s,
density in kg/m^3, pressure stiffness in m^2/s^2 (pressure ``p = k_p (rho - rho0)``),
viscosity in Pa s.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from . import checks

#: Stress models (docs/method.md §4-5). ``linear``: eq. 9 with the Bargteil flow rule.
#: ``non_newtonian``: eq. 9, flow rate divided by the stress magnitude (paper Fig. 1).
#: ``hyperelastic``: eq. 9 with squared singular values (paper Fig. 5), twice the St.
#: Venant-Kirchhoff stress. ``stvk``: the St. Venant-Kirchhoff stress itself, for
#: quantitative work (its small-strain stiffness equals the linear model's). A ``linear`` or
#: ``non_newtonian`` material on the variational force that cannot flow takes the corotated
#: stress instead of eq. 9's (``Material``'s docstring).
MODELS = ("linear", "non_newtonian", "hyperelastic", "stvk")
#: The unit of each fitted parameter (the module doc's SI), as fits print them.
UNITS = {"mu": "Pa", "lam": "Pa", "yield_stress": "Pa", "flow_rate": "1/s", "hardening": "Pa",
         "pressure_stiffness": "m^2/s^2", "viscosity": "Pa s"}
#: The models whose steady simple shear is a Bingham fluid of ``Material.shear_yield_stress``
#: and ``Material.plastic_viscosity`` (``Material.from_rheology``).
BINGHAM_MODELS = ("linear", "stvk")
MODEL_IDS = {name: k for k, name in enumerate(MODELS)}

#: Deformation models (docs/method.md §7, paper Fig. 8): the paper's ``incremental`` update, and the
#: comparison models ``rest`` (rest configuration and plastic F_p) and ``additive``
#: (additive Green strain); see ``warp_esph/sim/comparison.py``.
DEFORMATIONS = ("incremental", "rest", "additive")
DEFORMATION_IDS = {name: k for k, name in enumerate(DEFORMATIONS)}

#: Elastic pair forces (``warp_esph/sim/forces.py``): ``paper``, eqs. 10-13 of the paper;
#: ``variational``, minus the gradient of the elastic energy of the incremental fit
#: (``sum_i V_i psi(F_i)``), whose linear stiffness is symmetric (docs/physics.md).
ELASTIC_FORCES = ("paper", "variational")
ELASTIC_FORCE_IDS = {name: k for k, name in enumerate(ELASTIC_FORCES)}

#: SPH pressure pair forces (``warp_esph/sim/pressure.py``, docs/method.md §6): ``energy``,
#: the exact negative gradient of the SPH pressure energy ``sum_i m_i e_i(rho_i)``
#: (the poly6 density's own kernel gradient, ``p / rho^2`` pair weights), which does no net
#: work on a closed path of the particles; ``spiky``, Müller et al.'s ``(p_i + p_j) / 2``
#: along the spiky kernel's gradient (the paper's), the gradient of no energy, which keeps
#: the 16-across S = 0.5 slump creeping (docs/physics.md, the SPH pressure); ``energy_spiky``,
#: the exact negative gradient of the same energy of a density summed with the spiky kernel,
#: whose gradient does not vanish as two particles meet, so it holds merging particle layers
#: apart where the poly6 one lets them merge (docs/physics.md, "The Fig. 8
#: rest-configuration cube and the energy pressure force"): the default, since the poly6
#: energy's pairing gives a flowed pile a spurious strength (docs/physics.md, "The default
#: pressure force: energy_spiky"). ``isotropic``: ``energy_spiky``'s pressure (the same spiky
#: density and default ``k_p``) applied as each particle's stress ``-p_i I`` through its
#: neighbourhood's moment matrix, not along pairs, so a surface particle's own pressure forces
#: carry ``p V I`` where the pair forms' carry a load the yield test does not see
#: (docs/method.md §6, docs/physics.md, "The SPH pressure carries load the yield test does not
#: see"); not beside another pressure force in one model, nor with floor images.
PRESSURE_FORCES = ("energy", "spiky", "energy_spiky", "isotropic")
PRESSURE_FORCE_IDS = {name: k for k, name in enumerate(PRESSURE_FORCES)}
#: The forces whose pressure reads the spiky-kernel density (``State.pressure_density``).
SPIKY_DENSITY_FORCES = ("energy_spiky", "isotropic")

#: The default ``k_p = share * K / rho0`` of each pressure force (``K`` the bulk modulus).
#: Either adds about a quarter of ``K`` to the bulk stiffness: the energy force's pressure
#: is the virial pressure of its pair forces (``-dE_p/dV``), while the spiky force's pair
#: forces carry 0.47 of ``p`` on a uniformly compressed lattice (``h = 2 dx``; in the
#: continuum ``(p_i + p_j) / 2`` weights give half of ``grad p``), so ``K / (2 rho0)``, the
#: spiky force's default since it was the only one, adds 0.23 K through it
#: (docs/physics.md, the SPH pressure).
#: ``energy_spiky``'s 0.46 gives the energy force's small-strain bulk stiffness: the pressure
#: energy's curvature is ``k_p rho0 c^2`` with ``c = -(d rho / d eps_v) / rho`` of the SPH
#: density on a lattice (``h = 2 dx``), 1.055 for poly6 and 0.774 for the spiky density, so
#: ``0.25 (1.055 / 0.774)^2 = 0.464`` (docs/physics.md, "A pressure energy of a spiky density").
#: ``isotropic`` keeps ``energy_spiky``'s (the same pressure, only applied otherwise, so its
#: runs are the experimental flag's), which adds 0.44 ``K`` through its stress ``-p I``, not a
#: quarter: it applies ``p`` itself, where ``energy_spiky``'s pair virial is ``p c rho0 / rho~0``
#: = 0.63 ``p`` (``c`` = 0.774, the lattice's spiky sum ``rho~0`` = 1.24 ``rho0``; 0.28 ``K``),
#: still under the ``rho0 k_p`` that
#: ``Model.stable_dt`` allows for (``tests/test_isotropic_pressure.py``).
PRESSURE_BULK_SHARE = {"energy": 0.25, "spiky": 0.5, "energy_spiky": 0.46, "isotropic": 0.46}


def p_wave_speed(mu, lam, density, pressure_stiffness):
    """``sqrt((lam + 2 mu + rho0 k_p) / rho0)``, the speed the explicit step must resolve
    (docs/method.md §8); numbers or numpy arrays."""
    with np.errstate(over="ignore"):  # inf past the float range, which Material refuses by name
        return np.sqrt((lam + 2.0 * mu + density * pressure_stiffness) / density)


@dataclasses.dataclass(frozen=True)
class Material:
    """An elastoplastic material.

    ``deformation`` picks the deformation model (``DEFORMATIONS``): ``"incremental"`` (the
    paper's, default), or the Fig. 8 comparison models ``"rest"`` and ``"additive"``.

    ``elastic_force`` picks the elastic pair force (``ELASTIC_FORCES``): ``"variational"``
    (default), the exact negative gradient of the fit's elastic energy, or ``"paper"``, the
    paper's eqs. 10-13. The default is the one that passes the validation suite
    (docs/validation.md): a free-free bar rings at 0.999 / 1.000 of its frequency at 4 / 6
    particles across (paper: 0.88 / 0.92) and a near-yield column holds at 6 across, at rest
    with only its base yielding (paper: 2.86 x the 1-D theory, still moving; docs/validation.md,
    Notes); the paper's force
    has a non-symmetric stiffness, so an undamped elastic body gains energy at a rate that
    does not shrink with the time step (docs/physics.md) and a bent beam flutters. With the
    Fig. 8 comparison models (``"rest"``, ``"additive"``) the default is ``"paper"``; the
    variational force is defined for ``"incremental"`` and ``"rest"``. With ``"rest"`` it is
    the gradient of the total fit's energy against the rest neighbourhood, a function of the
    positions alone, so an undamped purely elastic body keeps its energy at the stable step
    (the incremental ``F <- dF F`` is path dependent and gains energy as ``dt^2``:
    docs/physics.md, "The energy of undamped elastic bodies"); it is not for plastic flow.
    Scenes that reproduce the paper's figures ask for ``"paper"`` explicitly.

    **What ``yield_stress`` and ``flow_rate`` mean.** The flow rule compares the Frobenius
    norm of the deviatoric stress, ``|s| = 2 mu |sigma - mean(sigma)|`` (``sigma`` the
    singular values of the elastic ``F``), with ``Y = yield_stress + hardening * alpha``
    (docs/method.md §4). So ``yield_stress`` is neither the shear nor the uniaxial yield
    stress a rheometer or a tensile test reports:

    * shear yield stress ``tau_y = Y / sqrt(2)`` (simple shear ``tau`` has ``|s| = sqrt(2) tau``);
    * uniaxial yield stress ``sigma_y = sqrt(3/2) Y`` (uniaxial ``sigma`` has ``|s| = sqrt(2/3) sigma``),
      von Mises' ``sigma_y = sqrt(3) tau_y``.

    Above yield the deviatoric elastic log strain relaxes at the rate
    ``flow_rate * (|s| - Y) / |s|`` (1/s), so in steady simple shear at rate ``gamma_dot``
    the shear stress is ``tau = tau_y + (mu / flow_rate) gamma_dot``: a Bingham fluid of
    plastic viscosity ``eta_p = mu / flow_rate`` (Pa s) once it flows (``model="linear"``
    and ``"stvk"``; the ``non_newtonian`` rule divides the rate by ``|s|`` once more, and
    ``hyperelastic`` stresses are twice the linear ones at small strain: measured in the
    same shear, it flows at twice the yield stress and plastic viscosity). The properties
    ``shear_yield_stress``, ``uniaxial_yield_stress`` and ``plastic_viscosity`` give these,
    and ``Material.from_rheology`` builds a material from them, for ``BINGHAM_MODELS``
    only (the others refuse)
    (``tests/test_units.py`` checks the relation in a simulated simple-shear test).

    ``hardening`` (Pa per unit of accumulated plastic strain ``alpha``) raises the yield stress
    to ``Y = yield_stress + hardening * alpha`` as the material flows; ``hardening < 0``
    softens it, down to 0 and no further (a yield stress is never negative). It must be
    above ``-2 mu``: the flow lowers ``|s|`` by ``2 mu`` per unit of ``alpha`` (small elastic
    strain), so at ``hardening <= -2 mu`` the yield stress falls at least as fast as the
    stress and a point that yields flows on until its yield stress is gone, however small the
    overstress, where above it the flow stops at a softened yield stress
    (``tests/test_units.py``, the softening test; docs/method.md §4).

    ``yield_stress = 0`` with ``flow_rate > 0`` flows at any deviatoric stress: a Maxwell
    fluid, in steady simple shear a Newtonian one of viscosity ``mu / flow_rate``
    (``tests/test_units.py``: 49.2 Pa s for 50 asked at ``E`` = 100 kPa, intercept 0).

    ``yield_stress = inf`` (or ``flow_rate = 0``) gives a purely elastic material. With the
    variational force, such a ``linear`` or ``non_newtonian`` material (the default
    ``Material.from_young(E, nu)`` is one) takes the corotated stress ``P = U diag(P^) V^T``,
    ``P^ = 2 mu (sigma - 1) + lam sum(sigma - 1)``, minus the gradient of the energy
    ``mu sum(sigma - 1)^2 + lam/2 (sum(sigma - 1))^2``, where eq. 9's ``U diag(sigma o P^) V^T``
    (the same at small strain) is the gradient of no energy, and gained energy on the
    conservative rest model that ``fit="auto"`` runs for it (docs/physics.md, "Choices"). A
    material that can flow, and one on the paper's force, keeps eq. 9.
    ``pressure_stiffness = None`` picks ``k_p = K / (4 rho0)`` (``K = lam + 2 mu / 3`` the
    bulk modulus) for the energy force, ``K / (2 rho0)`` for the spiky one and ``0.46 K /
    rho0`` for ``energy_spiky`` and ``isotropic`` (``PRESSURE_BULK_SHARE``): SPH pressure adds about a quarter of the bulk
    stiffness again, the "additional stability" of the paper's §4 (``isotropic``, at
    ``energy_spiky``'s ``k_p``, 0.44 of it). Use ``0`` to switch
    pressure off.

    ``pressure_force`` picks the SPH pressure pair force (``PRESSURE_FORCES``):
    ``"energy_spiky"`` (default), minus the gradient of the pressure's energy ``sum_i m_i
    e_i(rho~_i)`` with ``de/drho~ = p / rho~^2`` of a density ``rho~`` summed with the spiky
    kernel (its rest value per particle from the initial configuration; kept in
    ``State.pressure_density``, while ``State.density`` and the viscous volumes stay the
    poly6 SPH density for every force), whose push between two particles grows until they
    meet; ``"energy"``, the same energy of the poly6 density, whose push fades as two
    particles meet, so particle layers pressed closer than half a spacing merge and a flowed
    pile pairs its particles and stands taller; or ``"spiky"``, Müller et al.'s symmetrised
    pressure along the spiky kernel's gradient (the paper's), the gradient of no energy, which
    keeps a 16-across slumped yield-stress pile creeping at a flat rate where either energy
    force lets it come to rest; or ``"isotropic"``, ``energy_spiky``'s pressure applied as
    each particle's stress ``-p_i I`` through its neighbourhood's moment matrix (the
    variational force's map), so that a free-surface particle's own pressure forces have the
    virial ``p V I``, which the pair forms' do not (the unfused step runs it; it may not share
    a model with another pressure force, nor floor images) (docs/method.md §6). ``Model.stable_dt()`` bounds each force
    (docs/physics.md, "The step bound of undamped fast plastic flow").

    ``pair_repulsion = c`` (0, the default: off) adds the short-range pair potential
    ``U = (c_i k_p,i + c_j k_p,j)/2 sqrt(m_i m_j) (1 - r/r0)^3`` below ``r0 = h/4``
    (``pressure.pair_repulsion_force``; docs/method.md §6): it keeps apart two particles
    that a landing drives together, which the pressure forces' finite push lets meet
    (docs/physics.md, "landed as an option"). Not a fitted parameter.
    """

    mu: float
    lam: float
    yield_stress: float = math.inf
    flow_rate: float = 0.0
    hardening: float = 0.0
    density: float = 1000.0
    pressure_stiffness: float | None = None
    viscosity: float = 0.0
    model: str = "linear"
    clamp_pressure: bool = True
    deformation: str = "incremental"
    elastic_force: str | None = None
    pressure_force: str = "energy_spiky"
    pair_repulsion: float = 0.0

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        # Not a field: equality, hash, repr and asdict stay the resolved values'; replace() and
        # preset() read it so that a new deformation gets its model's default force (a defaulted
        # 'variational' kept through replace(deformation='additive') was refused, never asked for).
        set_("_elastic_force_defaulted", self.elastic_force is None)
        # Checked before the default force reads it: a numpy array compared to a name raised
        # numpy's 'truth value of an array is ambiguous', naming no field.
        checks.choice("Material.deformation", self.deformation, DEFORMATIONS)
        if self.elastic_force is None:
            # The variational force is defined only for the incremental fit (its energy's
            # gradient); the comparison models keep the force they were published with.
            set_("elastic_force", "variational" if self.deformation == "incremental" else "paper")
        mu = checks.positive("Material.mu", self.mu)
        set_("mu", mu)
        set_("lam", checks.greater_than("Material.lam", self.lam, -2.0 * mu / 3.0, "-2 mu / 3"))
        set_("yield_stress", checks.non_negative("Material.yield_stress", self.yield_stress, allow_inf=True))
        set_("flow_rate", checks.non_negative("Material.flow_rate", self.flow_rate))
        set_("hardening", _checked_hardening(self.hardening, mu))
        set_("density", checks.positive("Material.density", self.density))
        checks.choice("Material.pressure_force", self.pressure_force, PRESSURE_FORCES)
        if self.pressure_stiffness is None:
            derived = self.default_pressure_stiffness
            if not math.isfinite(derived):
                raise ValueError(
                    f"Material.mu = {self.mu!r}, Material.lam = {self.lam!r} and Material.density = {self.density!r} "
                    f"are not allowed together: the default pressure_stiffness they give, "
                    f"{PRESSURE_BULK_SHARE[self.pressure_force]} K / density, is not a finite number")
            set_("pressure_stiffness", derived)
        set_("pressure_stiffness", checks.non_negative("Material.pressure_stiffness", self.pressure_stiffness))
        set_("viscosity", checks.non_negative("Material.viscosity", self.viscosity))
        set_("pair_repulsion", checks.non_negative("Material.pair_repulsion", self.pair_repulsion))
        # The explicit step resolves this speed: past the float range it was inf, the stable step
        # 0, and a rollout of a given dt ran to NaN positions and returned them without a word.
        if not math.isfinite(float(p_wave_speed(self.mu, self.lam, self.density, self.pressure_stiffness))):
            raise ValueError(
                f"Material.mu = {self.mu!r}, Material.lam = {self.lam!r}, Material.density = {self.density!r} and "
                f"Material.pressure_stiffness = {self.pressure_stiffness!r} are not allowed together: their p-wave speed "
                "sqrt((lam + 2 mu + density pressure_stiffness) / density) is not a finite number")
        checks.choice("Material.model", self.model, MODELS)
        checks.choice("Material.deformation", self.deformation, DEFORMATIONS)
        checks.choice("Material.elastic_force", self.elastic_force, ELASTIC_FORCES)
        if self.elastic_force == "variational" and self.deformation == "additive":
            raise ValueError(
                f"Material.elastic_force = 'variational' is not allowed with deformation = {self.deformation!r}: "
                "it is the gradient of a fit's energy; use deformation = 'incremental' or 'rest', or elastic_force = 'paper'"
            )
        if not isinstance(self.clamp_pressure, bool):
            raise ValueError(f"Material.clamp_pressure = {checks.shorten(self.clamp_pressure)!r} is not allowed: must be True or False")

    @classmethod
    def from_young(cls, E: float, nu: float, **kwargs) -> "Material":
        """Material from Young's modulus ``E`` (Pa) and Poisson ratio ``nu`` in (-1, 0.5)."""
        E = checks.positive("E", E)
        nu = checks.number("nu", nu)
        if not -1.0 < nu < 0.5:
            raise ValueError(f"nu = {checks.shorten(nu)!r} is not allowed: must be in (-1, 0.5)")
        _check_fields("Material.from_young", kwargs)
        if {"mu", "lam"} & kwargs.keys():
            raise ValueError(f"{', '.join(sorted({'mu', 'lam'} & kwargs.keys()))} is not allowed in Material.from_young: "
                             "mu and lam are derived from E and nu")
        mu, lam = _lame(E, nu)
        return _from_young(cls(mu=mu, lam=lam, **kwargs), E, nu)

    @classmethod
    def from_rheology(
        cls,
        E: float,
        nu: float,
        *,
        shear_yield_stress: float | None = None,
        uniaxial_yield_stress: float | None = None,
        plastic_viscosity: float,
        **kwargs,
    ) -> "Material":
        """A Bingham-like material from the quantities a lab measures.

        ``E`` (Pa) and ``nu`` the elastic part (as ``from_young``); exactly one of
        ``shear_yield_stress`` (Pa, a rheometer's ``tau_y``) and ``uniaxial_yield_stress``
        (Pa, a compression or tensile test's ``sigma_y``); ``plastic_viscosity`` (Pa s,
        the Bingham ``eta_p``: ``tau = tau_y + eta_p gamma_dot`` in steady shear; a required
        keyword, ``math.inf`` for a material that never flows), which sets ``flow_rate = mu / eta_p``. See the class docstring for the derivation.
        A value whose derived ``yield_stress`` or ``flow_rate`` leaves the floats (or a flow
        rate that underflows to 0) is refused naming the quantity given, not the derived field."""
        if (shear_yield_stress is None) == (uniaxial_yield_stress is None):
            raise ValueError(
                f"shear_yield_stress = {shear_yield_stress!r} and uniaxial_yield_stress = {uniaxial_yield_stress!r} "
                "are not allowed together or both missing: give exactly one of them"
            )
        _check_fields("Material.from_rheology", kwargs)
        if {"mu", "lam"} & kwargs.keys():
            raise ValueError(f"{', '.join(sorted({'mu', 'lam'} & kwargs.keys()))} is not allowed in "
                             "Material.from_rheology: mu and lam are derived from E and nu")
        if "yield_stress" in kwargs or "flow_rate" in kwargs:
            raise ValueError(
                "yield_stress and flow_rate are not allowed in Material.from_rheology: they are derived from "
                "shear_yield_stress / uniaxial_yield_stress and plastic_viscosity"
            )
        Y = (lab_yield_stress("shear_yield_stress", shear_yield_stress) if shear_yield_stress is not None
             else lab_yield_stress("uniaxial_yield_stress", uniaxial_yield_stress))
        if plastic_viscosity is None:
            # Once the default, it was infinite: flow_rate 0, an elastic material on which the
            # yield stress given had no effect, without a word.
            raise ValueError("plastic_viscosity = None is not allowed in Material.from_rheology: give the Bingham plastic "
                             "viscosity (Pa s; flow_rate = mu / plastic_viscosity), without which the material never flows "
                             "(math.inf says so explicitly)")
        checks.positive("plastic_viscosity", plastic_viscosity, allow_inf=True)
        model = kwargs.get("model", "linear")
        checks.choice("Material.model", model, MODELS)  # a misspelt model named as such first
        checks.choice("Material.deformation", kwargs.get("deformation", "incremental"), DEFORMATIONS)
        if model not in BINGHAM_MODELS or kwargs.get("deformation", "incremental") != "incremental":
            what = (f"model = {model!r}" if model not in BINGHAM_MODELS
                    else f"deformation = {kwargs['deformation']!r}")
            raise ValueError(f"{what} is not allowed in Material.from_rheology: the Bingham relation holds for "
                             f"model {' or '.join(map(repr, BINGHAM_MODELS))} with deformation 'incremental' only "
                             "(give yield_stress and flow_rate to Material for the others)")
        flow_rate = lab_flow_rate(plastic_viscosity, cls.from_young(E, nu).mu,
                                  f"E = {checks.shorten(E)!r}, nu = {checks.shorten(nu)!r}")
        yield_given = (("shear_yield_stress", shear_yield_stress) if shear_yield_stress is not None
                       else ("uniaxial_yield_stress", uniaxial_yield_stress))
        return from_lab(cls.from_young(E, nu, yield_stress=Y, flow_rate=flow_rate, **kwargs),
                        {"yield_stress": yield_given, "flow_rate": ("plastic_viscosity", plastic_viscosity)})

    @classmethod
    def preset(cls, name: str, **overrides) -> "Material":
        """A named preset (see ``PRESETS``), with any field overridden. Fields the presets
        leave at their defaults follow the overrides they depend on, as ``Material(...)``
        would derive them: ``pressure_stiffness`` new moduli, a density or a
        ``pressure_force``, and ``elastic_force`` a ``deformation`` (the comparison models'
        is ``"paper"``), unless the overrides set them too."""
        checks.choice("preset", name, tuple(PRESETS))
        _check_fields("Material.preset", overrides)
        if {"mu", "lam", "density", "pressure_force"} & overrides.keys() and "pressure_stiffness" not in overrides:
            overrides["pressure_stiffness"] = None  # re-derive it from the new moduli / force
        return dataclasses.replace(PRESETS[name], **_following_force(PRESETS[name], overrides))

    def replace(self, **changes) -> "Material":
        """A copy with ``changes``. A ``pressure_stiffness`` at its default follows a new
        ``pressure_force`` (each force's default adds the same bulk stiffness) unless
        ``changes`` sets it; new moduli keep the old value. An ``elastic_force`` left to its
        default (not given to ``Material(...)``, a preset's) follows a new ``deformation``
        unless ``changes`` sets it: ``"paper"`` for the comparison models; one given keeps
        its value (``"variational"`` with ``deformation="additive"`` is refused)."""
        _check_fields("Material.replace", changes)
        if "pressure_force" in changes and "pressure_stiffness" not in changes and self.has_default_pressure_stiffness:
            changes["pressure_stiffness"] = None
        return dataclasses.replace(self, **_following_force(self, changes))

    @property
    def default_pressure_stiffness(self) -> float:
        """``k_p = PRESSURE_BULK_SHARE[pressure_force] * K / rho0`` (m^2/s^2)."""
        return PRESSURE_BULK_SHARE[self.pressure_force] * self.bulk_modulus / self.density

    @property
    def has_default_pressure_stiffness(self) -> bool:
        """Whether ``pressure_stiffness`` is ``default_pressure_stiffness`` (to rounding)."""
        return math.isclose(self.pressure_stiffness, self.default_pressure_stiffness, rel_tol=1e-9)

    @property
    def youngs_modulus(self) -> float:
        """``E = mu (3 lam + 2 mu) / (lam + mu)`` (Pa)."""
        return self.mu * (3.0 * self.lam + 2.0 * self.mu) / (self.lam + self.mu)

    @property
    def poisson_ratio(self) -> float:
        """``nu = lam / (2 (lam + mu))``."""
        return self.lam / (2.0 * (self.lam + self.mu))

    @property
    def bulk_modulus(self) -> float:
        """``K = lam + 2 mu / 3`` (Pa), which the default ``pressure_stiffness`` scales."""
        return self.lam + 2.0 * self.mu / 3.0

    @property
    def p_wave_speed(self) -> float:
        """The speed the explicit step must resolve (``p_wave_speed`` of its parameters)."""
        return float(p_wave_speed(self.mu, self.lam, self.density, self.pressure_stiffness))

    @property
    def shear_yield_stress(self) -> float:
        """``tau_y = yield_stress / sqrt(2)`` (Pa): the yield stress in simple shear
        (``BINGHAM_MODELS`` only: another model raises ValueError)."""
        self._check_bingham("shear_yield_stress")
        return self.yield_stress / math.sqrt(2.0)

    @property
    def uniaxial_yield_stress(self) -> float:
        """``sigma_y = sqrt(3/2) yield_stress`` (Pa): the yield stress in uniaxial tension or
        compression (``BINGHAM_MODELS`` only: another model raises ValueError)."""
        self._check_bingham("uniaxial_yield_stress")
        return math.sqrt(1.5) * self.yield_stress

    @property
    def plastic_viscosity(self) -> float:
        """Bingham plastic viscosity ``eta_p = mu / flow_rate`` (Pa s; ``inf`` without flow;
        ``BINGHAM_MODELS`` only: another model raises ValueError)."""
        self._check_bingham("plastic_viscosity")
        return math.inf if self.flow_rate == 0.0 else self.mu / self.flow_rate

    def _check_bingham(self, name: str) -> None:
        # Measured in steady simple shear (tests/test_units.py): hyperelastic flows at twice
        # the shear yield stress and plastic viscosity these would give, non_newtonian is no
        # Bingham fluid at all; a property that reported them anyway misled.
        if self.model not in BINGHAM_MODELS or self.deformation != "incremental":
            raise ValueError(f"Material.{name} is not allowed for model = {self.model!r}, deformation = "
                             f"{self.deformation!r}: the Bingham relation holds for model "
                             f"{' or '.join(map(repr, BINGHAM_MODELS))} with deformation 'incremental' only")

    @property
    def plastic(self) -> bool:
        """Whether the material can flow: a finite ``yield_stress`` and ``flow_rate > 0``."""
        return math.isfinite(self.yield_stress) and self.flow_rate > 0.0


#: The Lame parameters of Young's modulus and Poisson's ratio, as the refusals write them.
LAME_FORMULAS = {"mu": "E / (2 (1 + nu))", "lam": "E nu / ((1 + nu) (1 - 2 nu))"}


def _from_young(material: Material, E: float, nu: float) -> Material:
    """``material``, noting the ``E`` and ``nu`` its ``mu`` and ``lam`` came from (not a field:
    equality, ``asdict`` and ``replace`` ignore it) so that a model's precision check names
    them: ``E = 1e-39`` in float32 was refused as ``Material.mu = 3.84615e-40``, a value never given."""
    object.__setattr__(material, "_young", (E, nu))
    return material


def from_lab(material: Material, given: dict) -> Material:
    """``material``, noting the lab's values (``LAB_QUANTITIES``) its fields came from,
    ``{field: (lab name, value given)}`` (not a field, as ``_from_young``'s note), so that a
    model's precision check names them: ``shear_yield_stress = 1e39`` in float32 was refused as
    ``Material.yield_stress = 1.41421e+39``, a value never given."""
    object.__setattr__(material, "_lab", dict(given))
    return material


def lab_given(material: Material) -> dict:
    """``from_lab``'s note of ``material``, ``{}`` where it has none (a copy, ``replace``'s, is made anew)."""
    return getattr(material, "_lab", {})


def young_given(material: Material) -> tuple[float, float] | None:
    """``(E, nu)`` where ``material`` was made from them (``Material.from_young``, a scene
    table's ``E`` and ``nu``), else None (a copy with other values, ``replace``'s, is made anew)."""
    return getattr(material, "_young", None)


def _lame(E: float, nu: float) -> tuple[float, float]:
    """``(mu, lam)`` of Young's modulus ``E`` and Poisson's ratio ``nu`` (each checked by the
    caller), or a ValueError naming both where either leaves the floats (a huge ``E``, or ``nu``
    within 1e-16 of -1 or 0.5), or falls below float64's normal numbers (a subnormal or tiny
    ``E``; a subnormal ``nu``): the refusal named ``Material.mu = inf`` or ``Material.lam = inf``
    (a scene file's ``mu = inf``), or, at the model's build, ``Material.mu = 3.84e-321``,
    values the caller never gave."""
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    given = f"E = {checks.shorten(E)!r} and nu = {checks.shorten(nu)!r} are not allowed together: the Lame parameters " \
            f"they give, mu = {LAME_FORMULAS['mu']} = {mu:g} and lam = {LAME_FORMULAS['lam']} = {lam:g}"
    if not (math.isfinite(mu) and math.isfinite(lam)):
        raise ValueError(f"{given}, must be finite numbers; give a smaller E or a nu further from -1 and 0.5")
    # No precision holds a modulus below the smallest normal float64 (Model refuses it in either
    # dtype, or as mu = 0 here): refused now, by what was given, not at the build by mu.
    tiny = float(np.finfo(np.float64).tiny)
    if not mu >= tiny or lam != 0.0 and abs(lam) < tiny:
        # mu holding, lam is below it by nu's factor: nu is the tiny one.
        cure = "a larger E" if not mu >= tiny else "nu = 0 or a nu further from 0"
        raise ValueError(f"{given}, must be at least {tiny:.3g} (mu) and 0 or at least {tiny:.3g} in size (lam), the "
                         f"smallest normal float64; give {cure}")
    return mu, lam


def _checked_hardening(hardening, mu: float) -> float:
    """``hardening`` if it is a number above ``-2 mu``. A flow of ``d alpha`` lowers the flow
    stress by ``|hardening| d alpha`` and the deviatoric stress by ``2 mu d alpha`` (``|s| = 2 mu
    |dev ln sigma|`` at small elastic strain, every model's flow rule): at ``hardening <= -2 mu``
    the flow stress falls at least as fast as the stress, so a particle that yields at all
    flows on until its yield stress is gone, whatever the load (-1e30 did so at its first
    flow), where a softening above it stops at a softened yield stress (docs/method.md §4)."""
    v = checks.number("Material.hardening", hardening)
    if not v > -2.0 * mu:
        raise ValueError(
            f"Material.hardening = {checks.shorten(hardening)!r} is not allowed: must be > -2 mu = {-2.0 * mu:g}: a "
            "softening of 2 mu or more lowers the yield stress at least as fast as the flow relaxes the stress, so a "
            "particle that yields flows until its yield stress is gone, whatever the load")
    return v


def _following_force(material: "Material", changes: dict) -> dict:
    """``changes`` with ``elastic_force = None`` where ``material``'s force was its default
    and ``changes`` does not set one: it is derived again, from a new ``deformation`` (the
    comparison models' is ``"paper"``), and stays defaulted in the copy (a copy given the
    resolved value would keep it through a later change of ``deformation``)."""
    if "elastic_force" not in changes and getattr(material, "_elastic_force_defaulted", False):
        return {**changes, "elastic_force": None}
    return changes


def _check_fields(where: str, given) -> None:
    """Every name in ``given`` is a ``Material`` field: a misspelt one raised Python's
    TypeError from the dataclass."""
    fields = [f.name for f in dataclasses.fields(Material)]
    unknown = sorted(set(given) - set(fields))
    if unknown:
        lab = "".join(lab_value_note(name) for name in unknown)
        hint = f"{lab} (give the fields, or make the material with Material.from_rheology)" if lab else ""
        raise ValueError(f"{', '.join(map(repr, unknown))} is not allowed in {where}: must be one of {', '.join(fields)}{hint}")


#: The values a lab measures, which ``Material.from_rheology`` (and a scene file's material
#: table) take: name -> (the field each sets, how, and how the field converts back). Given in
#: place of a field (a preset's override, a fitted or swept parameter), they had been refused
#: naming the fields alone.
LAB_QUANTITIES = {
    "shear_yield_stress": ("yield_stress", "yield_stress = sqrt(2) shear_yield_stress", "yield_stress / sqrt(2)"),
    "uniaxial_yield_stress": ("yield_stress", "yield_stress = sqrt(2/3) uniaxial_yield_stress", "sqrt(3/2) yield_stress"),
    "plastic_viscosity": ("flow_rate", "flow_rate = mu / plastic_viscosity", "mu / flow_rate"),
}


def lab_yield_stress(name: str, value, elastic: str = "use Material.from_young") -> float:
    """The ``yield_stress`` of a lab's ``shear_yield_stress`` or ``uniaxial_yield_stress``
    (``name``) of ``value`` (``LAB_QUANTITIES``), refused by the value given where it is past
    the floats (``Material.from_rheology`` and a scene file's material table). ``elastic``: the
    refusal's advice for a material that never yields, in the caller's terms."""
    factor = {"shear_yield_stress": math.sqrt(2.0), "uniaxial_yield_stress": math.sqrt(2.0 / 3.0)}[name]
    Y = factor * checks.non_negative(name, value)
    if not math.isfinite(Y):
        # sqrt(2) x 1.5e308 is inf: an elastic material, the yield stress given without effect.
        raise ValueError(f"{name} = {checks.shorten(value)!r} is not allowed: {LAB_QUANTITIES[name][1]} must be a finite "
                         f"number (for a material that never yields, {elastic})")
    return Y


def lab_flow_rate(plastic_viscosity, mu: float, moduli: str) -> float:
    """The ``flow_rate = mu / plastic_viscosity`` of a lab's plastic viscosity, for a material of
    shear modulus ``mu`` (``moduli``: what gave it, as the refusal names it), refused by the
    value given where the rate is past the floats or 0 (``math.inf``: 0, a material that never
    flows)."""
    eta = checks.positive("plastic_viscosity", plastic_viscosity, allow_inf=True)
    flow_rate = mu / eta
    if not math.isfinite(flow_rate) or flow_rate == 0.0 and math.isfinite(eta):
        # 1e-320 Pa s was refused as Material.flow_rate = inf, a value the caller never gave;
        # a flow rate that underflows to 0 is an elastic material, the viscosity given without effect.
        raise ValueError(f"plastic_viscosity = {checks.shorten(plastic_viscosity)!r} is not allowed with {moduli}: "
                         f"flow_rate = mu / plastic_viscosity = {mu:g} / {eta:g} = {flow_rate:g} must be a finite number "
                         "above 0 (math.inf: a material that never flows)")
    return flow_rate


def lab_value_note(name: str, what: str = "field") -> str:
    """``"; NAME is a lab's value, not a WHAT: FORMULA"`` where ``name`` is one of
    ``LAB_QUANTITIES``, else ``""``: the clause a refusal of that name as a field adds."""
    return f"; {name} is a lab's value, not a {what}: {LAB_QUANTITIES[name][1]}" if name in LAB_QUANTITIES else ""


def material_setting_note(name, role: str, cli: bool) -> str:
    """``"; NAME is a material setting, not a ROLE parameter: set it in ..."`` where ``name`` is
    a field of ``Material`` that is not per particle (``Model.MATERIAL_FIELDS``), such as
    ``pair_repulsion``, ``pressure_force`` or ``density``, else ``""``. ``role``: ``fitted``
    or ``swept``; ``cli``: the command line's words (the scene's material table) or Python's
    (``Material``). Without it fit's and sweep's refusals of such a field read as of a typo,
    not as a choice made where the material is made."""
    from .model import Model  # noqa: PLC0415  (model imports this module)

    if not isinstance(name, str) or name in Model.MATERIAL_FIELDS or name not in {f.name for f in dataclasses.fields(Material)}:
        return ""
    where = f"the scene's material table ({name} = ...)" if cli else f"the Material (Material(..., {name}=...))"
    return f"; {name} is a material setting, not a {role} parameter: set it in {where}"


# Presets: soft, kitchen-scale materials that run stably at 1-2 cm spacing with the
# default time steps. Moduli are of the order measured for the real materials
# (bread dough E ~ 10^4 Pa, modelling clay ~ 10^5 Pa, soft rubber ~ 10^5-10^6 Pa)
# and chosen so each one shows its character in a drop onto the ground. The explicit
# step dissipates nothing by itself: an undamped body rings after an impact for as
# long as the run lasts, so each preset carries some viscosity (Pa s) to settle.
#: The named materials of ``Material.preset`` and scene files' ``preset`` (the reasons above).
PRESETS: dict[str, Material] = {
    # Flows under its own weight, slowly, and keeps the new shape (the paper's Fig. 6).
    "dough": Material.from_young(2.0e4, 0.3, yield_stress=150.0, flow_rate=20.0, hardening=0.0, density=1150.0, viscosity=10.0),
    # Stiffer, yields under impact, hardens as it is worked.
    "clay": Material.from_young(1.0e5, 0.3, yield_stress=2000.0, flow_rate=50.0, hardening=5000.0, density=1800.0, viscosity=20.0),
    # Elastic: bounces back to its rest shape. (With the paper's elastic force the ball of
    # the rubber_bounce scene gains internal kinetic energy after landing instead of
    # coming to rest, docs/physics.md.)
    "rubber": Material.from_young(2.0e5, 0.4, density=1100.0, viscosity=2.0),
    # Non-Newtonian (paper Fig. 1): resists sudden stress, flows under small stress.
    "putty": Material.from_young(5.0e4, 0.3, yield_stress=100.0, flow_rate=2.0e4, density=1200.0, viscosity=10.0, model="non_newtonian"),
    # Low yield, fast flow: slumps into a puddle.
    "toothpaste": Material.from_young(1.0e4, 0.3, yield_stress=50.0, flow_rate=200.0, density=1300.0, viscosity=5.0),
}
