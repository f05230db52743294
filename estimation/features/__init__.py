"""Features and matches: SIFT keypoints and descriptors, pairwise matching, tracks built from matches."""
