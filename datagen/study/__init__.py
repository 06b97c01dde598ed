"""What accuracy costs in time: study scenes, runs of our solvers and of Blender's, metrics."""
