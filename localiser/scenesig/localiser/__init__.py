"""Online localisation: detector, solver, sliding-window pose graph, SE(2) snapping, the weak localisers
(scene signatures, ORB, SIFT), replay of a survey run, its outputs and metrics.

After C. McManus, B. Upcroft and P. Newman, "Learning place-dependent features for long-term vision-based
localisation", Autonomous Robots 39(3), 2015 -- cited in the code as "McManus et al. 2015, §N / eq. N".
Imports ``mapping``, ``signatures`` and ``surveys``.
"""
