"""Cameras, the plane geometry of MPIs (plane depths, homographies, virtual poses) and camera paths."""
