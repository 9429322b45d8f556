"""Looking at what moves: a rendezvous needs the camera on the other robot.

The camera looks forward with a narrow field of view, so two robots can pass a few metres from
each other without either reading the other's tag. The LIDAR sees all around: returns that
fall, as a compact group, into space the map knows to be free (with free cells all around)
are something that moved there — most likely another robot. While the robot still has robots
outside its team, it then turns toward that group, holds still a moment so the camera gets a
few frames, and goes back to its path. A cooldown keeps it from doing this too often.

Farther away than a tag can be read, up to ``approach_range_m``, such a group is something to
go and see: once it has been seen in a few consecutive scans near one place, the robot drives
toward it (tracking it scan by scan) until it is close enough to read a tag well, then turns
toward it and holds as above. "Well" means close: a tag's heading is only informative within a
metre or so, and without it a merge needs sightings from places a metre apart. Both robots
usually see each other at once, so they close in together. The approach gives up when the
thing is lost or takes too long.

A tag read from too far to merge on is a call: the server passes it to both robots. The one
that read it knows where the other is (range and bearing are good even where the tag's heading
is not) and goes there; the one that was seen learns roughly where the reader stands (through
the unreliable heading) and goes toward the moving thing its LIDAR sees nearest that place.
When it sees none there, the place is no guide (past 3 m a tag's heading is off by tens of
degrees), so it stops and turns once on the spot: the reader is coming, and once its tag is in
view the robot knows where the reader is, too. But a robot whose LIDAR sees all round and past
the reader's distance, and finds nothing standing at that distance, does not answer: no robot
read its tag from there (a tag misread, or read where no robot stood). Each further sighting
keeps the approach alive, so a robot that stands still behind the other's LIDAR shadow is not
lost. A call from within tag range cuts short whatever else the robot was looking at or
driving to: it faces the other robot and both hold still a few seconds, so that each reads the
other's tag.
"""

from server.lookout.lookout import Lookout, LookParams, NullLookout
from server.lookout.movers import moving_object, moving_objects, objects_at_range

__all__ = ["LookParams", "Lookout", "NullLookout", "moving_object", "moving_objects",
           "objects_at_range"]
