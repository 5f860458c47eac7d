"""The detect stage: marker detection per frame, its worker pool, its on-disk cache, the family scan."""
