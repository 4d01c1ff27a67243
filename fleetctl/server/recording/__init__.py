"""MCAP recording of relayed frames: one more consumer of the relay core, with its own
bounded queue and a worker process of its own (docs/server.md, "Recording").

``config``: the ``recording:`` section; ``rules``: which frames (RE2 per identity, cached);
``recorder``: the relay's side (queue, pipe, worker life cycle, metrics); ``worker``: the
worker process's main loop; ``writer``: frames to rotating MCAP files within the disk
bounds; ``mcapfile``: one rosbag2-compatible file; ``files``: the directory (listing,
reading open files, complete copies, deletion by the bounds).
"""
