"""Road-marking rasterization (Kim, Liu & Myung section 2.1): elevation grid -> traversable cells ->
adaptive intensity threshold -> per-tile marking rasters."""
