"""The simulated survey world (the embedded default data).

Public entry points:

* :func:`scenesig.surveys.sim.simulate.simulate` / ``scenesig simulate`` -- write survey runs;
* :class:`scenesig.surveys.sim.world.World` -- the procedural world (``World.load(world.json)`` regenerates it;
  :func:`scenesig.surveys.sim.scene.render_view` renders one view of it, image and true depth);
* :func:`place_views` -- one place under many conditions;
* ``scenesig bench realism`` -- ORB realism table; ``scenesig bench render`` -- frames/s.
"""
from .views import place_views, place_views_with_poses, view_pose
from .world import World

__all__ = ["World", "place_views", "place_views_with_poses", "view_pose"]
