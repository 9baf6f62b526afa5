"""The simulated survey world (the embedded default data).

Public entry points:

* :func:`surveys.sim.simulate.simulate` / ``scenesig simulate`` -- write survey runs;
* :class:`surveys.sim.world.World` -- the procedural world (``World.load(world.json)`` regenerates it;
  ``World.render(T_world_camera, condition)`` gives image and true depth);
* :func:`place_views` -- one place under many conditions;
* ``python -m surveys.sim.realism`` -- ORB realism table; ``python -m surveys.sim.bench`` -- frames/s.
"""
from .views import place_views, place_views_with_poses, view_pose
from .world import World

__all__ = ["World", "place_views", "place_views_with_poses", "view_pose"]
