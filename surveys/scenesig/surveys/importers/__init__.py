"""Importers and exporters between the survey-run folder and the formats users hold.

One module per format, each with plain functions and a ``default_config`` dict that a caller's ``config``
overrides (:func:`scenesig.surveys.settings.merge_settings`: a misspelt option is an error):

* :mod:`.kitti_raw` -- a KITTI raw drive (images, OXTS GPS/IMU, calibration chain);
* :mod:`.kapture` -- NAVER's kapture text format, both ways;
* :mod:`.tum_rgbd` -- a TUM RGB-D sequence (``rgb.txt`` + ``groundtruth.txt``);
* :mod:`.euroc` -- a EuRoC MAV / ASL folder (``mav0/camN`` + ``state_groundtruth_estimate0``);
* :mod:`.rosbag` -- ROS 1 / ROS 2 (sqlite3, MCAP) bags, both ways (optional package ``rosbags``);
* :mod:`.photometric` -- the darkening used to make a night-like replay of a day run.

Every importer builds a :class:`scenesig.surveys.run.SurveyRun` and hands it to :func:`scenesig.surveys.run.write_run`,
which writes beside the destination and renames into place only when complete: an interrupted import
never leaves a half-written run. Bad input raises :class:`scenesig.surveys.errors.DataError` naming the file
and line.
"""
