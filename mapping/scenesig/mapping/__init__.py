"""Offline map building: places along a reference run, landmark refinement (temporal check, depth sweep,
Levenberg-Marquardt with Huber weights), georeferencing, the point-feature map, the map store.

After C. McManus, B. Upcroft and P. Newman, "Learning place-dependent features for long-term vision-based
localisation", Autonomous Robots 39(3), 2015 -- cited in the code as "McManus et al. 2015, §N / eq. N".
Imports ``signatures`` and ``surveys``.
"""
