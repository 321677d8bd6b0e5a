"""Perception front end: camera model, segmentation, mask filtering, stereo, detection."""
