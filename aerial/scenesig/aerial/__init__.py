"""scenesig: aerial -- UAV-to-map scene matching against geo-referenced satellite tiles.

MRSM-CC (Jin et al., "A multi-region scene matching based localisation system for UAVs", Journal
of Navigation 2016) with its single-image baseline SISM, point-feature baselines (SIFT, ORB) and a
scene-signature matcher, the Monte-Carlo trial generator of Jin et al.'s protocol, and sequence localisation.
"""
