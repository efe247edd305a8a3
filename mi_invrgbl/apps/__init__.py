"""Applications of fitted scenes: relighting, night, object insertion, LiDAR simulation."""
