"""Multi-view geometry shared by every stage: RANSAC, triangulation, absolute pose, similarity alignment."""
