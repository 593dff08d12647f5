#!/bin/sh
# Make a private CA and a certificate for the Zenoh router, valid for 127.0.0.1 and
# localhost, with the openssl command-line tool. Usage: make-certs.sh [DIR] [HOST_IP]
# (default DIR: certs, HOST_IP: 127.0.0.1). For a router on another host, pass its address.
# Keys are written mode 600; keep ca.key offline once the certificates are made.
set -eu
dir=${1:-certs}
ip=${2:-127.0.0.1}
mkdir -p "$dir"
umask 077
openssl req -x509 -newkey rsa:2048 -nodes -days 365 -subj "/CN=glider-hil test CA" \
    -keyout "$dir/ca.key" -out "$dir/ca.pem" 2>/dev/null
openssl req -newkey rsa:2048 -nodes -subj "/CN=glider-hil-router" \
    -keyout "$dir/router.key" -out "$dir/router.csr" 2>/dev/null
printf 'subjectAltName=IP:%s,DNS:localhost\nbasicConstraints=CA:FALSE\nkeyUsage=digitalSignature,keyEncipherment\nextendedKeyUsage=serverAuth,clientAuth\n' "$ip" > "$dir/router.ext"
openssl x509 -req -in "$dir/router.csr" -CA "$dir/ca.pem" -CAkey "$dir/ca.key" \
    -CAcreateserial -days 365 -extfile "$dir/router.ext" -out "$dir/router.pem" 2>/dev/null
rm -f "$dir/router.csr" "$dir/router.ext" "$dir/ca.srl"
chmod 644 "$dir/ca.pem" "$dir/router.pem"
echo "wrote $dir/ca.pem, $dir/router.pem and their keys"
