"""CAD-guided view planning, feedback planners, robot kinematics and reachability."""
