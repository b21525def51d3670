"""Sensor-skin design tools (thesis 4.5.4, 4.8.1): a sensor layout projected onto a base mesh, a
stretch-minimizing unwrap, simulated-annealing nesting and cutting-plotter toolpaths (``xm skin``).

Pure library code: meshes and files in, meshes, polygons, reports and files out. Lengths are in mm.
"""
