"""Direct shear in ours and in LAMMPS from the same fills; print the friction angles and one JSON line.

Scene: benchmarks/peers/lammps_shear.py COMPARISON_SCENE (270 grains, 1 and 2 kPa, Hertz-Mindlin-Coulomb
with mu = 0.5, restitution 0.3, no rolling resistance, Earth gravity; ours on the CPU in double precision).
Per specimen the peak and residual friction angles through the origin (tau = sigma tan(phi_0) over its two
normal stresses); the means and standard deviations over the replicas, Mohr-Coulomb over every point, and
the lid's rise at the end of the shear (dilation > 0).

Run from the repository root::

    python benchmarks/peers/run_lammps_shear.py --replicas 10 --out runs/shear_lammps
"""

import argparse
import json
import os
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from benchmarks.peers import lammps_shear  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--replicas", type=int, default=3, help="specimens of each (K)")
    parser.add_argument("--out", default=None, help="folder for our shear report (default: a temporary one)")
    args = parser.parse_args()

    from cosim.lab.scene import lab_scene_from_text, resolve_lab

    plan = resolve_lab(lab_scene_from_text(lammps_shear.COMPARISON_SCENE))
    with tempfile.TemporaryDirectory() as tmp:
        result = lammps_shear.compare(plan, args.replicas, args.out or os.path.join(tmp, "ours"))
    print(f"direct shear, {result['grains']} grains, {args.replicas} specimens each (angles through the origin)")
    for name in ("ours", "lammps"):
        side = result[name]
        cells = []
        for state in ("peak", "residual"):
            stats, fit = side[f"{state}_stats"], side[f"{state}_fit"]
            cells.append(
                f"{state} {stats['mean']:.1f} +- {stats['std']:.1f} deg "
                f"(Mohr-Coulomb {fit['friction_angle_deg']:.1f} deg, c {fit['cohesion_pa']:.0f} Pa)"
            )
        rise = side["rise_stats"]
        cells.append(f"lid rise {rise['mean'] * 1e6:.0f} +- {rise['std'] * 1e6:.0f} um")
        print(f"  {name:7s} {'; '.join(cells)}; {side['seconds']:.0f} s")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
