"""Front end: image/grid features, scan features, ICP scan matching, place recognition for loop closure."""
