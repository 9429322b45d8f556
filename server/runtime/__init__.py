"""The server as a running process: the bus, threads, processes and files around the core.

The daemon opens the Zenoh router and runs the node; the node admits messages (registry,
clocks), queues them fairly (inbox) and hands them one typed item at a time (work) to the core
on its worker thread, stepping a lockstep simulation whole (lockstep). The state survives
crashes and full disks (journal, snapshot, keeper, writer); outputs are written on a thread of
their own; the slow work runs in process pools; several workers share robots (cluster,
handover). Nothing below this package does I/O.
"""
