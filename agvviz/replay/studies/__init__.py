"""Study stages: Monte-Carlo trials (paper 000) and CNOEM grid cells (paper 002)."""
