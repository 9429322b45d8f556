"""Wire messages of mrslam: typed structs, key expressions, codec and JSON Schema export."""

from schemas.codec import MESSAGE_TYPES, decode, encode
from schemas.errors import SchemaError
from schemas.messages import (
    Event,
    Hypothesis,
    LidarSweep,
    MapUpdate,
    Message,
    RobotEstimate,
    RobotStates,
    RobotStatus,
    Scan,
    TagDetection,
    TagDetections,
    TeamCoverage,
    VelocityCommand,
    quantise_ranges_mm,
    ranges_from_mm,
)
from schemas.sim import (
    SimClock,
    SimGroundTruth,
    SimImage,
    SimLidar,
    SimMotorCommand,
    SimOdometry,
    SimStepAck,
    TruePose,
    TrueRelative,
)
from schemas.types import NO_RETURN_MM, SCHEMA_VERSION

__all__ = [
    "MESSAGE_TYPES", "NO_RETURN_MM", "SCHEMA_VERSION", "Event", "Hypothesis", "LidarSweep",
    "MapUpdate", "Message", "RobotEstimate", "RobotStates", "RobotStatus", "Scan", "SchemaError",
    "SimClock", "SimGroundTruth", "SimImage", "SimLidar", "SimMotorCommand", "SimOdometry",
    "SimStepAck", "TagDetection", "TagDetections", "TeamCoverage", "TruePose", "TrueRelative",
    "VelocityCommand", "decode", "encode", "quantise_ranges_mm", "ranges_from_mm",
]
