#!/usr/bin/env bash
# Set up a Raspberry Pi (Raspberry Pi OS / Debian, 64-bit) as an mrslam robot.
#   usage: sudo deploy/pi-setup.sh ROBOT_ID SERVER_HOST [CERTS_DIR]
#   e.g.   sudo deploy/pi-setup.sh r1 server.lab.local /tmp/certs
# CERTS_DIR holds ca.pem, ROBOT_ID.pem and ROBOT_ID.key from deploy/zenoh/make-certs.sh; without
# it the agent connects over plain TCP (a closed lab network only).
# Idempotent: re-running updates the install and keeps /etc/mrslam/agent.yaml if it exists.
set -euo pipefail
rid=${1:?usage: pi-setup.sh ROBOT_ID SERVER_HOST [CERTS_DIR]}
host=${2:?usage: pi-setup.sh ROBOT_ID SERVER_HOST [CERTS_DIR]}
certs=${3:-}
src="$(cd "$(dirname "$0")/.." && pwd)"
[ "$(id -u)" = 0 ] || { echo "run as root (sudo)" >&2; exit 1; }
[[ "$rid" =~ ^[a-z][a-z0-9_-]{0,15}$ ]] || { echo "bad robot id: $rid" >&2; exit 1; }

# 1. system packages: Python, venv, OpenCV's runtime libraries, udev, time sync
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq python3 python3-venv python3-pip libgl1 libglib2.0-0 udev \
  systemd-timesyncd >/dev/null

# 2. a system user in the serial and video groups
id mrslam >/dev/null 2>&1 || useradd --system --home /var/lib/mrslam --shell /usr/sbin/nologin \
  --groups dialout,video mrslam
install -d -o mrslam -g mrslam /var/lib/mrslam
install -d -m 0755 /etc/mrslam

# 3. the venv with the agent's extras only (no gtsam, open3d or scikit-image)
[ -x /opt/mrslam/venv/bin/python ] || python3 -m venv /opt/mrslam/venv
/opt/mrslam/venv/bin/pip install -q --disable-pip-version-check --upgrade pip
/opt/mrslam/venv/bin/pip install -q --disable-pip-version-check "$src[agent]"

# 4. stable device names for the LIDAR and the base
install -m 0644 "$src/deploy/udev/99-mrslam.rules" /etc/udev/rules.d/99-mrslam.rules
udevadm control --reload-rules
udevadm trigger --subsystem-match=tty

# 5. certificates and the Zenoh client config
if [ -n "$certs" ]; then
  install -d -m 0750 -g mrslam /etc/mrslam/certs
  install -m 0644 "$certs/ca.pem" "$certs/$rid.pem" /etc/mrslam/certs/
  install -m 0640 -g mrslam "$certs/$rid.key" /etc/mrslam/certs/
  python3 "$src/deploy/zenoh/config.py" agent --certs /etc/mrslam/certs \
    --connect "tls/$host:7447" --robot "$rid" > /etc/mrslam/zenoh-agent.json5
  endpoint="tls/$host:7447"
  zenoh_config="/etc/mrslam/zenoh-agent.json5"
else
  endpoint="tcp/$host:7447"
  zenoh_config="null"
fi

# 6. the agent's config (kept if present: it holds the robot's measured geometry)
if [ ! -f /etc/mrslam/agent.yaml ]; then
  cat > /etc/mrslam/agent.yaml <<YAML
robot_id: $rid
backend: hardware
bus:
  connect: ["$endpoint"]
  zenoh_config: $zenoh_config
  connect_timeout_ms: -1
hardware:
  lidar: {port: /dev/rplidar, baud: 115200, beams: 360, mount_yaw_rad: 0.0}
  base: {port: /dev/mrslam-base, track_m: 0.30, wheel_radius_m: 0.05, ticks_per_rev: 1000}
  camera: {enabled: true, device: 0, calibration: /etc/mrslam/camera.yaml, rate_hz: 5}
detector: {body_radius_m: 0.13}
YAML
  echo "wrote /etc/mrslam/agent.yaml: measure track_m, wheel_radius_m, ticks_per_rev and the" \
    "other robots' body radius at LIDAR height (detector.body_radius_m; 0: tags alone), and add" \
    "/etc/mrslam/camera.yaml (K, dist) before driving" >&2
fi

# 7. the service
install -m 0644 "$src/deploy/systemd/mrslam-agent.service" /etc/systemd/system/
systemctl daemon-reload
systemctl enable --now mrslam-agent.service
echo "mrslam agent $rid enabled; check: journalctl -u mrslam-agent -f;" \
  "LIDAR: /opt/mrslam/venv/bin/mrslam lidar-dump --port /dev/rplidar --scans 3" >&2
