"""Scene signatures: HOG pyramids, the 296 candidate shapes, mining banks of linear HOG-patch classifiers by
iterative discriminative clustering, detecting a bank, and the point-feature front ends of the baselines.

After C. McManus, B. Upcroft and P. Newman, "Learning place-dependent features for long-term vision-based
localisation", Autonomous Robots 39(3), 2015 -- cited in the code as "McManus et al. 2015, §N / eq. N".
Imports only ``surveys``.
"""
