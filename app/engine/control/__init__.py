"""Controllers: compiled step functions and the small objects that wrap them."""
