#!/usr/bin/env bash
# Make a private CA, a router certificate (for 127.0.0.1/localhost and an optional host name) and a
# client certificate under DIR (default ./certs). Example: deploy/zenoh/make_certs.sh certs mapper.lan
set -euo pipefail
dir=${1:-certs}; host=${2:-localhost}
mkdir -p "$dir"; cd "$dir"
openssl req -x509 -newkey rsa:2048 -nodes -days 365 -subj "/CN=argus-ca" -keyout ca.key -out ca.crt 2>/dev/null
for name in router client; do
  openssl req -newkey rsa:2048 -nodes -subj "/CN=argus-$name" -keyout $name.key -out $name.csr 2>/dev/null
  printf "subjectAltName=IP:127.0.0.1,DNS:localhost,DNS:%s\nbasicConstraints=CA:FALSE\n" "$host" > $name.ext
  openssl x509 -req -in $name.csr -CA ca.crt -CAkey ca.key -CAcreateserial -days 365 -extfile $name.ext \
    -out $name.crt 2>/dev/null
  rm -f $name.csr $name.ext
done
echo "certificates in $(pwd): ca.crt router.{crt,key} client.{crt,key}"
