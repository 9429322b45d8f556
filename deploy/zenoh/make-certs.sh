#!/usr/bin/env bash
# Create a private CA, a server certificate and one client certificate per robot for mutual TLS.
# The robot id is the certificate's common name: the router's access-control rules use it to
# let each robot publish only under mrslam/robot/<id>/.
#   usage: make-certs.sh OUT_DIR SERVER_HOST [ROBOT_ID...]
#   e.g.   make-certs.sh /etc/mrslam/certs server.lab.local r1 r2 r3
set -euo pipefail
out=${1:?usage: make-certs.sh OUT_DIR SERVER_HOST [ROBOT_ID...]}
host=${2:?usage: make-certs.sh OUT_DIR SERVER_HOST [ROBOT_ID...]}
shift 2
mkdir -p "$out"
cd "$out"
umask 077

key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:prime256v1 -out "$1" 2>/dev/null; }

if [ ! -f ca.pem ]; then
  key ca.key
  openssl req -x509 -new -key ca.key -out ca.pem -days 3650 -subj "/CN=mrslam-ca" 2>/dev/null
fi

sign() {  # sign NAME COMMON_NAME SUBJECT_ALT_NAME
  key "$1.key"
  openssl req -new -key "$1.key" -out "$1.csr" -subj "/CN=$2" 2>/dev/null
  printf 'subjectAltName=%s\nbasicConstraints=CA:FALSE\nkeyUsage=digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\n' \
    "$3" > "$1.ext"
  openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -out "$1.pem" \
    -days 825 -extfile "$1.ext" 2>/dev/null
  rm -f "$1.csr" "$1.ext"
}

case "$host" in
  *[!0-9.]*) san="DNS:$host" ;;
  *) san="IP:$host" ;;
esac
sign server mrslam-server "$san,DNS:localhost,IP:127.0.0.1"
for rid in "$@"; do
  sign "$rid" "$rid" "DNS:$rid"
done
echo "certificates in $out: ca.pem, server.{pem,key}${*:+, }$(printf '%s.{pem,key} ' "$@")" >&2
