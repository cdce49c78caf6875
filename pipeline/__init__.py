"""Pipeline: runs sequences end to end (modes field / frontend / fused) and evaluates them."""
