"""measure: bead width along the track from a photo or a flatbed scan, plus the synthetic camera."""
