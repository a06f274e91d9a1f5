"""Where data enters and leaves the graph: PyBullet HyQ on soft ground (node sim_bridge), MCAP replay and recording."""
