"""The server's algorithms on recorded data, without a bus: ``mrslam slam-log`` on CARMEN
logs and ROS bags (slam_log, logs), merging recorded sessions (offline_merge), and scoring
against reference relations or ground truth (evaluation, scoring)."""
