"""Two-view geometry: fundamental and essential matrices, relative pose and its chirality check."""
