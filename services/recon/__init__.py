"""3-D reconstruction: 2-D keypoints per camera -> triangulated hand and object keypoints."""
