"""Loop latency race: scan sent at the robot -> spin plan received at the robot."""
