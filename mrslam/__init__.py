"""mrslam: multi-robot active SLAM over Zenoh with GTSAM factor graphs."""

__version__ = "0.1.0"
