#!/usr/bin/env bash
# Makes the TLS identity and the bearer token that deploy/docker-compose.yml and the Kubernetes
# manifests expect, in deploy/secrets/ (ignored by git): a self-signed certificate for
# localhost, 127.0.0.1 and the names given as arguments (EC P-256, one year), its key, and a
# random 64-character token. Use a certificate from your own CA in production; clients trust
# this one with `alignist --ca-file deploy/secrets/server.pem`.
#
#   bash deploy/make-secrets.sh [DNS-NAME ...]
#   # Kubernetes (namespace alignist):
#   kubectl -n alignist create secret tls alignist-tls \
#     --cert=deploy/secrets/server.pem --key=deploy/secrets/server.key
#   kubectl -n alignist create secret generic alignist-token --from-file=token=deploy/secrets/token
set -euo pipefail
dir="$(cd "$(dirname "$0")" && pwd)/secrets"
mkdir -p "$dir"
names="DNS:localhost,IP:127.0.0.1,DNS:alignist,DNS:alignist.alignist.svc.cluster.local"
for n in "$@"; do names="$names,DNS:$n"; done
if [[ -e "$dir/server.pem" || -e "$dir/token" ]]; then
  echo "$dir already holds secrets; remove them first to make new ones" >&2
  exit 1
fi
umask 077
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes \
  -keyout "$dir/server.key" -out "$dir/server.pem" -days 365 -subj "/CN=alignist" \
  -addext "subjectAltName=$names" -addext "basicConstraints=critical,CA:FALSE" \
  -addext "keyUsage=critical,digitalSignature" -addext "extendedKeyUsage=serverAuth" 2>/dev/null
openssl rand -hex 32 > "$dir/token"
# The server in the container runs as uid 10001: it must be able to read them.
chmod 644 "$dir/server.pem" "$dir/server.key" "$dir/token"
echo "wrote $dir/server.pem, server.key and token (names: $names)"
