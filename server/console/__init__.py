"""The operator console (``mrslam server --console PORT``; docs/console.md)."""
