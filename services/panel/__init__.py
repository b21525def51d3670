"""The web dashboard (viser): 3-D scene, tactile heatmaps, camera view, service status, recording."""
