"""The contact law as Warp functions (docs/physics.md section 1), generic in precision.

`contact_functions(hi, lo, law).contact_law` is a @wp.func that turns one contact (overlap,
normal, relative motion, history) into the force and rolling torque on the particle.
Terms that the ContactLaw switches off are removed at compile time (wp.static), so
they cost nothing. Geometry and history use the first type, the force law's scalars the second:
a wall's or wheel's contact calls it with (hi, lo), a grain pair with (lo, lo) once it has taken
its differences in hi (soil.solver). The callers store the history in `mid` (soil.precision) and
convert it on the way in and out.
"""

import math
from dataclasses import dataclass

import warp as wp

from .materials import (
    PAIR_COHESION,
    PAIR_DAMPING,
    PAIR_E_STAR,
    PAIR_G_STAR,
    PAIR_ROLLING,
    PAIR_SHEAR_ROOT,
    PAIR_STICK_SPEED,
    PAIR_TAN_SLIP,
    PAIR_TAN_STICK,
)
from .precision import kernel_factory

LAW_VERSION = 2
"""Changes whenever the contact law's equations change, so that beds settled under another law
are not reused from a cache (2: the passive stick/slip switch, docs/physics.md section 1.3)."""


@dataclass(frozen=True)
class ContactLaw:
    """Which terms of the contact model a scene turns on."""

    damping: bool = True
    """Lehr normal damping and Kelvin tangential damping."""
    friction: bool = True
    """Tangential Kelvin element with stick/slip (phi_h, phi_g, v_Tmin)."""
    rolling: bool = False
    """Elastic-plastic rolling resistance torque, capped at mu_r R* |F_N|."""
    cohesion: bool = False
    """Cohesive attraction cohesion * pi R* delta inside the overlap."""
    twisting: bool = False
    """Elastic-plastic twisting resistance about the normal (the Mindlin patch's, no parameter)."""

    @property
    def spin(self) -> bool:
        """Whether contacts keep a spin history (rolling and/or twisting angles)."""
        return self.rolling or self.twisting


def spin_history_type(scalar, law: ContactLaw):
    """The Warp vector of one contact's spin history in `scalar` (hi in the law, mid as stored):
    the rolling angle [rad] (3 components), and with twisting the twist angle about the normal
    [rad] as a 4th."""
    return wp.types.vector(4 if law.twisting else 3, scalar)


@kernel_factory
def contact_functions(hi, lo, law: ContactLaw):
    """The contact @wp.func for precision types (hi, lo) and the switches in `law`."""
    vec_hi = wp.types.vector(3, hi)
    vec_spin = spin_history_type(hi, law)
    DAMPING, FRICTION, ROLLING, COHESION = law.damping, law.friction, law.rolling, law.cohesion
    TWISTING = law.twisting

    @wp.func
    def rolling_part(h: vec_spin):
        """The rolling angle [rad] (3,) of a spin history."""
        return vec_hi(h[0], h[1], h[2])

    if TWISTING:

        @wp.func
        def twist_part(h: vec_spin):
            """The twist angle about the normal [rad] of a spin history."""
            return h[3]

        @wp.func
        def spin_history(rolling: vec_hi, twist: hi):
            """A spin history from a rolling angle [rad] (3,) and a twist angle [rad]."""
            return vec_spin(rolling[0], rolling[1], rolling[2], twist)

    else:

        @wp.func
        def twist_part(h: vec_spin):
            """No twist angle without twisting resistance."""
            return hi(0.0)

        @wp.func
        def spin_history(rolling: vec_hi, twist: hi):
            """A spin history from a rolling angle [rad] (3,) (the twist is not kept)."""
            return rolling

    @wp.func
    def rotate_into_plane(h: vec_hi, n: vec_hi):
        # History is kept in the tangent plane; when the normal turns, turn the history
        # with it and keep its length (a frame-indifferent spring).
        before = wp.dot(h, h)
        h = h - wp.dot(h, n) * n
        after = wp.dot(h, h)
        if after > hi(0.0):
            h = h * wp.sqrt(before / after)
        return h

    @wp.func
    def contact_law(
        normal: vec_hi,
        overlap: hi,
        relative_velocity: vec_hi,
        relative_spin: vec_hi,
        radius_eff: lo,
        mass_eff: lo,
        pair: wp.array2d(dtype=lo),
        row: int,
        tangential_in: vec_hi,
        spin_in: vec_spin,
        dt: hi,
    ):
        """Force [N] and rolling/twisting torque [N m] on particle i, and its new histories.

        normal: unit vector from particle i towards its partner; overlap [m] > 0;
        relative_velocity: velocity of i's contact point minus the partner's [m/s];
        relative_spin: angular velocity of i minus the partner's [rad/s].

        Every damper is c = 2 D sqrt(m k) of its own stiffness k; the stiffnesses are
        multiples of the normal one (k_T / k = 4 G* / E*, a pair constant; k_r / k =
        2.25 mu_r^2 R*^2), so one square root serves all three. Limits are compared as
        squares: a sliding contact is the only one that needs a length.
        """
        ov = lo(overlap)
        sqrt_rd = wp.sqrt(radius_eff * ov)
        e_star = pair[row, PAIR_E_STAR]
        damping_ratio = pair[row, PAIR_DAMPING]
        # Hertz: F = 4/3 E* sqrt(R*) delta^1.5, tangent stiffness k = 2 E* sqrt(R* delta).
        normal_stiffness = lo(2.0) * e_star * sqrt_rd
        fn = lo(4.0 / 3.0) * e_star * sqrt_rd * ov
        approach_speed = wp.dot(relative_velocity, normal)
        damper = lo(0.0)  # 2 D sqrt(m* k): the normal damper [N s/m]
        if wp.static(DAMPING):
            # Lehr: c = 2 D sqrt(m* k), mass-scaled, so e does not depend on impact speed.
            damper = lo(2.0) * damping_ratio * wp.sqrt(mass_eff * normal_stiffness)
            fn = fn + damper * lo(approach_speed)
        fn = wp.max(fn, lo(0.0))  # a contact pushes, it never pulls (cohesion aside)
        force = -hi(fn) * normal
        if wp.static(COHESION):
            force = force + hi(pair[row, PAIR_COHESION] * lo(math.pi) * radius_eff * ov) * normal

        tangential = vec_hi()
        if wp.static(FRICTION):
            vt = relative_velocity - approach_speed * normal
            tangential = rotate_into_plane(tangential_in, normal) + vt * dt
            kt = lo(8.0) * pair[row, PAIR_G_STAR] * sqrt_rd  # Mindlin tangential stiffness
            kelvin = -(hi(kt) * tangential)
            if wp.static(DAMPING):
                kelvin = kelvin - hi(damper * pair[row, PAIR_SHEAR_ROOT]) * vt  # 2 D sqrt(m* k_T)
            stick_limit = hi(fn * pair[row, PAIR_TAN_STICK])
            stick_speed = hi(pair[row, PAIR_STICK_SPEED])
            vt_squared = wp.dot(vt, vt)
            slip_limit = hi(fn * pair[row, PAIR_TAN_SLIP])
            kelvin_squared = wp.dot(kelvin, kelvin)
            sticks = kelvin_squared <= stick_limit * stick_limit and vt_squared <= stick_speed * stick_speed
            if sticks or kelvin_squared <= slip_limit * slip_limit:
                force = force + kelvin  # the Kelvin element carries the load
            else:
                # Slip (docs/physics.md section 1.3): the element holds at most the slip force
                # F_N tan(phi_g). Its spring is cut to that force along itself and the force is
                # the spring's, so leaving stick never loads the spring, and the cut only takes
                # energy out: the switch is passive. Setting the spring to the full slip force
                # instead (when slipping by speed) made energy at every switch and drove the
                # high-frequency oscillation in which stick cannot occur.
                spring_force = hi(kt) * wp.length(tangential)
                if spring_force > slip_limit:
                    tangential = tangential * (slip_limit / spring_force)
                force = force - hi(kt) * tangential

        rolling = vec_hi()
        torque = vec_hi()
        if wp.static(ROLLING):
            mu_r = pair[row, PAIR_ROLLING]
            spin = relative_spin - wp.dot(relative_spin, normal) * normal
            rolling = rotate_into_plane(rolling_part(spin_in), normal) + spin * dt
            # elastic-plastic spring-dashpot rolling resistance (Ai et al. 2011)
            kr = lo(2.25) * mu_r * mu_r * radius_eff * radius_eff * normal_stiffness
            torque = -hi(kr) * rolling
            limit = hi(mu_r * radius_eff * fn)
            squared = wp.dot(torque, torque)
            if squared > limit * limit:
                # plastic: the spring is cut to the limit (it never gains energy), as for sliding
                torque = torque * (limit / wp.sqrt(squared))
                if kr > lo(0.0):
                    rolling = -torque / hi(kr)
                else:
                    rolling = vec_hi()
            elif wp.static(DAMPING):
                # 2 D sqrt(I* k_r), I* = 1.4 m* R*^2: 1.5 sqrt(1.4) mu_r R*^2 times the normal damper
                torque = torque - hi(lo(1.5 * math.sqrt(1.4)) * mu_r * radius_eff * radius_eff * damper) * spin
        twist = hi(0.0)
        if wp.static(TWISTING):
            # Twisting resistance about the normal from the Mindlin contact patch of radius
            # a = sqrt(R* delta) (Marshall 2009): stiffness k_T a^2 / 2, damper c_T a^2 / 2,
            # limit 2/3 a F_N tan(phi_g); elastic-plastic like the rolling resistance.
            patch_squared = radius_eff * ov
            twist_rate = wp.dot(relative_spin, normal)
            twist = twist_part(spin_in) + twist_rate * dt
            k_twist = lo(4.0) * pair[row, PAIR_G_STAR] * sqrt_rd * patch_squared  # (8 G* a) a^2 / 2
            moment = -hi(k_twist) * twist
            limit = hi(lo(2.0 / 3.0) * wp.sqrt(patch_squared) * fn * pair[row, PAIR_TAN_SLIP])
            if wp.abs(moment) > limit:
                moment = wp.sign(moment) * limit
                if k_twist > lo(0.0):
                    twist = -moment / hi(k_twist)
                else:
                    twist = hi(0.0)
            elif wp.static(DAMPING):
                moment = moment - hi(lo(0.5) * damper * pair[row, PAIR_SHEAR_ROOT] * patch_squared) * twist_rate
            torque = torque + moment * normal
        return force, torque, tangential, spin_history(rolling, twist)

    return dict(
        contact_law=contact_law,
        rotate_into_plane=rotate_into_plane,
        spin_history=spin_history,
        rolling_part=rolling_part,
    )
