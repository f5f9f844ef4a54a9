"""Maps: landmark map, occupancy grid (log-odds), topological map."""
