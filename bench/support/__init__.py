"""Harnesses the benchmarks share with the tests: a real ``mrslam server`` process and stand-in
robots on loopback (``fleet``), network-security helpers (``netsec``) and the bad inputs of every
command (``bad_inputs``). Tests may import these; nothing here imports ``tests``."""
