#!/bin/sh
# Certificates for the compose fleet over mutual TLS (docker/compose.tls.yaml): one CA for the
# fleet, a certificate for the router naming the address robots connect to, one per robot.
#
#   docker/certs.sh OUT [SAN] [ROBOTS]      e.g.  docker/certs.sh docker/certs DNS:router 3
#
# SAN: what the router's certificate names (default DNS:router, the compose service name;
# IP:127.0.0.1 for a router on the host's loopback). Writes, one folder per container (each is
# mounted read-only at /certs and holds nothing the container does not need):
#   OUT/ca/ca.key, ca.pem                the CA; ca.key never leaves this folder
#   OUT/router/ca.pem, router.pem, router.key
#   OUT/robot-<id>/ca.pem, robot.pem, robot.key
# The same openssl steps as docs/deploy.md section 1. The containers run as uid 1000, which must be
# able to read the keys: run this as that user, or chown the folders to 1000 afterwards.
set -eu
OUT=${1:?usage: docker/certs.sh OUT [SAN] [ROBOTS]}
SAN=${2:-DNS:router}
ROBOTS=${3:-3}
umask 077
mkdir -p "$OUT/ca" "$OUT/router"
cd "$OUT"
key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }
key ca/ca.key
openssl req -x509 -new -key ca/ca.key -sha256 -days 365 -subj "/CN=shapefleet fleet CA" \
    -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" -out ca/ca.pem
# sign NAME_DIR FILE SUBJECT EXTENSIONS
sign() {
    key "$1/$2.key"
    openssl req -new -key "$1/$2.key" -subj "$3" -out "$1/$2.csr"
    printf '%b' "$4" > "$1/$2.ext"
    openssl x509 -req -in "$1/$2.csr" -CA ca/ca.pem -CAkey ca/ca.key -CAcreateserial -sha256 -days 365 \
        -extfile "$1/$2.ext" -out "$1/$2.pem" 2>/dev/null
    rm "$1/$2.csr" "$1/$2.ext"
    cp ca/ca.pem "$1/ca.pem"
}
sign router router "/CN=shapefleet router" "subjectAltName=$SAN\nextendedKeyUsage=serverAuth\nbasicConstraints=CA:FALSE\n"
ID=0
while [ "$ID" -lt "$ROBOTS" ]; do
    mkdir -p "robot-$ID"
    sign "robot-$ID" robot "/CN=shapefleet robot $ID" "extendedKeyUsage=clientAuth\nbasicConstraints=CA:FALSE\n"
    ID=$((ID + 1))
done
chmod 644 ca/ca.pem router/*.pem robot-*/*.pem
chmod 755 router robot-*
echo "certificates in $OUT: CA, router ($SAN), robots 0..$((ROBOTS - 1))"
