"""Bundle adjustment of cameras and points as a GTSAM factor graph with projection factors."""
