"""ReacherRearrange and FrankaRearrange (Geom, OneGeom, Ycb, OneYcb): a torque-controlled robot
among four objects (one for `One*`) in a bordered table tray, mirroring bulb's `RearrangeEnv`
(facts: `../shared/reference/bulb-multiobject.md`; numbers and behaviour of contactrika/bulb).

The scene is composed with `dm_control.mjcf`: a floor plane, the tray (bulb's `borders.urdf` at
scale 0.8: four border boxes 0.84 x 0.04 x 0.08 m around a 0.8 x 0.8 m visual bottom), the robot
and the objects attached as sub-models (objects with free joints; `bulbjax.assets` for YCB).
What is mirrored:
- versions 0-11: the object list is bulb's list number `version % 6`, geom colours bulb's
  `GEOM_COLORS[version]`, the tray the version's texture as its mean colour (versions 6-11
  black). `version="random"` draws one per world and episode: the model then holds every
  object any version needs (a union with multiplicity) and parks the unused ones far above the
  scene with per-world gravity compensation (as the incline domains do).
- episode 200 steps; one env step is one of bulb's `stepSimulation` calls (dt 0.01 s, 2 solver
  substeps): MuJoCo steps 0.005 s, 2 per env step, the torque held.
- action a in [-1, 1] per controlled joint (bulbjax's convention; bulb's [0, 1] action is
  (a + 1) / 2): torque = clip(a, -1, 1) * max_torque. Reacher: 3 N m per joint. Franka: the
  URDF's efforts (87 x 4, 12 x 3 N m) plus gravity compensation (MuJoCo's bias force, bulb's
  inverse dynamics at zero acceleration), the sum clipped to the efforts; fingers fixed.
- joint limits as bulb enforces them after every step: Reacher joints beyond (31/32, 26/32) pi
  are put back on the limit with their velocity reversed; Franka joints outside the URDF's
  range are put back with zero velocity.
- reset: random robot pose (Reacher: U(+-0.75 pi) per joint; Franka: see `FrankaRearrange`),
  each object at x, y ~ U[-0.15, 0.15], z ~ U[0.03 (Ycb) or 0.04 (Geom), 0.075] with bulb's
  orientation draw (a uniform 4-vector in [0, 1]^4, normalised, as PyBullet's x, y, z, w);
  20 steps of free physics to let the objects settle; then 10 steps of random torques in
  +-max_torque / 2 (a ~ U[-0.5, 0.5]).
- done when an object leaves [-0.45, 0.45]^2 x [-0.05, 0.20] m, the end effector (the COM of
  bulb's end-effector link, as PyBullet's `getLinkState`) is more than 0.2 m above the tallest
  object (twice bulb's z times its z scale) or outside |x|, |y| <= 0.5; reward per step
  (1 - mean over objects of min(1, xy distance to its target)) / 200, targets (0.2, -0.2) for
  boxes and cans and (0.2, 0.2) for everything else.
- state (bulb's order, in [-1, 1]): sin and cos of every robot joint (the Franka's fixed fingers
  included, as bulb's `get_qpos` reports them); 12 properties per object (rgb, bulb's dims,
  shape id, mass, restitution, lateral/rolling/spinning friction, normalised by bulb's ranges;
  static); x, y, z per object (clipped to the box above, normalised); the rotation matrix per
  object (row-major). Groups `robot`, `object_static`, `object_position`,
  `object_orientation`. `state.info["lowdim_raw"]`: joint angles and speeds, each object's
  position (m), quaternion (w, x, y, z), linear velocity (m/s, world) and angular velocity
  (rad/s, body frame, MuJoCo's free joint), and the end effector's position.
- cameras: Reacher top-down (distance 0.40, yaw 90, pitch -89, target (0, 0, 0)); Franka
  distance 0.44, yaw 90, pitch -65, target (0.05, 0, 0); vertical FOV 90.

Known differences from bulb:
- bulb's `reacher.xml`, `cube.urdf`, `cylinder.urdf` and table textures are not in the stored
  repository: the reacher is written from the reference's numbers (heights, hand sizes and
  mass assumed, see `mjcf_assets/reacher_rearrange.xml`); cube = bulb's block (box 0.05 x 0.10 x
  0.15 m, 0.05 kg), cylinder radius 0.06, half-height 0.06, 0.2 kg; its contact parameters
  (restitution 0, lateral friction 0.5) assumed; tray colours are the textures' mean colours.
- The reacher follows the reference's numbers (2 kg links, armature 1, damping 1: a slow arm,
  ~0.4 rad in 0.6 s at full torque). bulb loaded its `reacher.xml` with PyBullet's `loadMJCF`,
  which ignores geom masses, joint damping and armature (measured on this file:
  `pybullet_compat/rearrange.py`, `docs/parity/rearrange_report.json`), so bulb's arm may have
  been far lighter and faster than the numbers say.
- The Panda is `pybullet_data`'s (bulb used its own `franka_small_fingers.urdf`, not stored):
  its fingers are longer, and at bulb's rest pose their tips touch the floor.
- bulb's rotation-matrix entries come from `quat2mat` applied to PyBullet's (x, y, z, w)
  quaternion, which that function reads as (w, x, y, z): bulb's nine numbers are the matrix of a
  permuted quaternion. Here they are the object's true rotation matrix.
- bulb's code leaves the target markers commented out (`create_visual_area` "impacts
  physics"), so by default no targets are drawn here either. `show_targets=True`
  (`bulbjax.make(..., show_targets=True)`, `bulbjax render --show-targets`) draws them as
  visual-only discs on the tray floor (radius 5 cm; violet at (0.2, -0.2) for boxes and cans,
  lime at (0.2, 0.2) for everything else; bulb's would-be markers were 1 cm translucent
  spheres); the physics is unchanged by them.
- YCB objects' body frames are their centres of mass (as in the incline domains; bulb places
  the mesh origin); positions in the state are COM positions.
- Contacts are MuJoCo's soft contacts with friction 0.5 everywhere (Bullet multiplies the two
  coefficients, 0.5-1.0 each); restitution (1.0 for spheres and borders in bulb) and the
  spheres' rolling/spinning friction (0.001) are left out; the robot does not collide with
  the tray's borders or with itself (bulb: self-collision on); the Reacher does not touch the
  floor, the Franka does.
- bulb's Franka skips `stepSimulation` entirely when the commanded torque is all zeros (an
  `allclose(torque, 0)` early return); here physics always steps.
- During the reset's settle, object speeds are capped at 1 m/s and 10 rad/s (MuJoCo pushes
  objects that start inside each other apart faster than Bullet; uncapped, light spheres could
  be thrown off the table).
- Every reset of a batch runs the settle (30 env steps of physics) for all worlds whenever any
  world resets, as MJX steps all worlds together.
"""

from __future__ import annotations

from bulbjax.envs.objects.franka_rearrange import (  # noqa: F401
    EE_POS_MAX, EE_POS_MIN, FRANKA_BASE, FRANKA_CAMERA, FRANKA_EFFORTS, FRANKA_REST, FrankaRearrange,
    FrankaRearrangeGeom, FrankaRearrangeOneGeom, FrankaRearrangeOneYcb, FrankaRearrangeYcb)
from bulbjax.envs.objects.reacher_rearrange import (  # noqa: F401
    REACHER_CAMERA, REACHER_LIMITS, ReacherRearrange, ReacherRearrangeGeom, ReacherRearrangeOneGeom,
    ReacherRearrangeOneYcb, ReacherRearrangeYcb)
from bulbjax.envs.objects.rearrange_base import Rearrange
from bulbjax.envs.objects.rearrange_scene import (  # noqa: F401  (the domain's constants, one import away)
    SHAPE_BOX, SHAPE_CYLINDER, SHAPE_MESH, SHAPE_SPHERE,
    NUM_VERSIONS,
    NUM_LISTS,
    EPISODE_STEPS,
    BULLET_DT,
    BULLET_SUBSTEPS,
    SETTLE_STEPS,
    RANDOM_TORQUE_STEPS,
    SETTLE_MAX_SPEED,
    SETTLE_MAX_SPIN,
    OBJ_XYZ_MIN,
    OBJ_XYZ_MAX,
    EE_XY_MAX,
    EE_ABOVE_OBJECTS,
    INIT_XY,
    INIT_Z_MAX,
    TARGETS,
    TARGET_RADIUS,
    TARGET_HALF_HEIGHT,
    TARGET_RGBA,
    TRAY_SCALE,
    PARK_HEIGHT,
    NAN_RETRIES,
    OBJECT_LISTS,
    GEOM_COLOURS,
    TABLE_RGB,
    PROP_NAMES,
    PROP_MIN,
    PROP_MAX,
    CYLINDER_DEFAULT_DIMS,
    GeomInfo,
    GEOM_INFO,
    YCB_DYNAMICS,
    OBJECT_CONAFFINITY,
    FRICTION,
    geom_model,
    is_box_or_can,
    object_half_height,
    rearrange_state_spec,
    rearrange_raw_state_spec,
    ANGLE_GROUP,
    angle_target_spec,
    angle_targets)

REARRANGE_CLASSES: tuple[type[Rearrange], ...] = (
    ReacherRearrangeGeom, ReacherRearrangeOneGeom, ReacherRearrangeYcb, ReacherRearrangeOneYcb,
    FrankaRearrangeGeom, FrankaRearrangeOneGeom, FrankaRearrangeYcb, FrankaRearrangeOneYcb)
