"""The Soil Contact Model (SCM): a fast terrain of a deformable height field, in Warp kernels.

A regular grid of nodes (spacing h) holds the soil height. Each step, every node under a
wheel's footprint casts a vertical ray up onto the wheels (the same shapes as the DEM's:
soil.geometry GrouserWheel, exactly; MeshWheel, through Warp's mesh ray query) and finds the
wheel surface above it. A node the wheel reaches below the soil's plastic surface is in
contact; with z its sinkage below its reference level, its normal pressure is elastic-plastic:

    sigma = min(K_e (z - z_p), (k_c / b + k_phi) z^n)      (Bekker's curve is the yield limit)

where z_p is the node's plastic sinkage (raised to z - sigma / K_e when the node yields: the
rut stays, and a second pass reloads elastically until it reaches the Bekker curve again)
and b is the contact patch's width (the smaller of its extents along the axle and across it:
the span of its contact nodes plus one spacing); an optional damping R adds R times the wheel
surface's speed into the soil. Where several wheels reach a node, the lowest surface presses it.
The pressure acts along the wheel surface's normal on the wheel-surface area above the node
(h^2 / |n_z|), so its vertical part is sigma h^2. The shear stress opposes the slip of the
wheel surface over the node (Mohr-Coulomb strength, Janosi-Hanamoto mobilisation):

    tau = (c + sigma tan(phi)) (1 - exp(-j / K))

with j the node's shear displacement: the slip speed of the wheel surface over the node,
integrated while the node is in contact (reset to 0 when the wheel leaves it). A step holds the
wheels at their pose at its start (the plastic flow and j are first order in the step).
Optional bulldozing moves the volume a patch displaces to its rims, then lets slopes steeper
than an erosion angle slide.

Memory does not grow with the distance travelled: the grid is a window of fixed size that
follows a centre (the wheels' mean hub position, or a given point) in whole node steps. It is
a ring buffer: node (I, J) of the infinite grid lives in slot (I mod nx, J mod ny); a slot
that a new node enters is reset to the undisturbed soil, so ruts older than the window's
reach are forgotten. A step works only each wheel's box (the nodes under the footprint of the
cylinder that holds it, plus one spacing; the nodes a box left are released: no contact, no
shear displacement), and a slot is reset when a box first reaches it: the cost of a step is
that of the wheels' footprints, not of the window (bulldozing, which lets any slope in the
window slide, works every node as well).

Kernel discipline as the DEM's: one generic kernel source per precision (hi = the precision's
`hi` type for every stored and summed quantity), no atomics, every sum in a fixed order
(per wheel: nodes in storage order in chunks, then the chunks in order), no host reads inside a
step (a step is graph-capturable), so runs repeat and resume bit for bit.

    from soil import GrouserWheel
    from soil.scm import ScmParameters, ScmTerrain
    dry_sand = ScmParameters(k_c=0.99e3, k_phi=1528.43e3, n=1.1, cohesion=1.04e3, friction_angle=28,  # degrees
                             janosi_k=0.02, elastic_stiffness=4e8, node_spacing=0.005)  # Wong's dry sand
    terrain = ScmTerrain(dry_sand, [GrouserWheel(0.1, 0.05)], window=(1.0, 0.5))
    terrain.advance(end_time=0.1, dt=1e-3, position=[[0, 0, 0.08]], orientation=[[1, 0, 0, 0]],
                    velocity=[[0.01, 0, 0]], angular_velocity=[[0, 0.12, 0]])
    contact = terrain.wheel_contact()        # force [N], torque about the hub [N m], nodes, sinkage [m]
"""

from .kernels import scm_kernels
from .terrain import ScmParameters, ScmTerrain, WheelContact, check_grid, grid_memory, grid_shape

__all__ = ["ScmParameters", "ScmTerrain", "WheelContact", "check_grid", "grid_memory", "grid_shape", "scm_kernels"]
