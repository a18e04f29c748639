#!/bin/sh
# Certificates for a TLS lab router (deploy/zenoh-router-tls.json5), made with the openssl
# command-line tool (OpenSSL 1.1.1 or 3.x; Ubuntu 22.04 ships 3.0): a lab CA, a server
# certificate for the router and one client certificate per relay and per host. No crypto of
# our own: openssl makes every key and signature.
#
#   deploy/make-certs.sh [-d DIR] [-r ROUTER_NAME]... [--days N] [--new-ca] CLIENT_NAME...
#
#   -d DIR           where the files go (default: ./certs); made with mode 700
#   -r NAME          a DNS name or IP address clients reach the router by (repeatable; the first is
#                    its common name). Clients check it: connect to tls/NAME:7447 with one of them.
#                    Default: localhost and 127.0.0.1
#   --days N         how long the router and client certificates are valid (default 365)
#   --new-ca         make a new CA even if DIR holds one (see "Rotating" in deploy/README.md)
#   CLIENT_NAME      one client certificate each, its common name being the name: the router's
#                    access control tells relays from hosts by it (relay-<robot>, host-<pc>), so
#                    use the names deploy/zenoh-router-tls.json5 lists
#
# Makes DIR/ca.pem (give to everyone), DIR/ca.key (the CA's key: keep it off the network),
# DIR/router.pem + router.key and DIR/<name>.pem + <name>.key per client. Keys are EC P-256, in
# PKCS#8 PEM, mode 600. An existing CA in DIR is reused, so running the script again renews
# the router and client certificates without touching the others' trust.
set -eu

dir=certs
days=365
new_ca=no
routers=""
usage() {  # $1: exit status (0: asked for with --help, to stdout)
    if [ "$1" = 0 ]; then
        sed -n '6,17p' "$0" | sed 's/^# \{0,1\}//'
    else
        sed -n '6,17p' "$0" | sed 's/^# \{0,1\}//' >&2
    fi
    exit "$1"
}
while [ $# -gt 0 ]; do
    case "$1" in
        -d) [ $# -ge 2 ] || usage 2; dir=$2; shift 2 ;;
        -r) [ $# -ge 2 ] || usage 2; routers="$routers $2"; shift 2 ;;
        --days) [ $# -ge 2 ] || usage 2; days=$2; shift 2 ;;
        --new-ca) new_ca=yes; shift ;;
        -h|--help) usage 0 ;;
        -*) echo "make-certs.sh: unknown option $1" >&2; usage 2 ;;
        *) break ;;
    esac
done
[ -n "$routers" ] || routers="localhost 127.0.0.1"
for name in "$@"; do
    case "$name" in
        ''|*[!A-Za-z0-9._-]*|router|ca)
            echo "make-certs.sh: client name '$name': use letters, digits, '.', '_', '-' (not router or ca)" >&2
            exit 2 ;;
    esac
done
command -v openssl >/dev/null || { echo "make-certs.sh: openssl is not installed" >&2; exit 1; }

umask 077
mkdir -p "$dir"
chmod 700 "$dir"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

new_key() {  # $1: key file
    openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null
}

is_ip() {
    case "$1" in
        *:*) return 0 ;;                              # IPv6
        *[!0-9.]*) return 1 ;;
        *.*.*.*) return 0 ;;
        *) return 1 ;;
    esac
}

# $1: name (file stem), $2: common name, $3: extendedKeyUsage, $4: subjectAltName
issue() {
    new_key "$dir/$1.key"
    openssl req -new -key "$dir/$1.key" -subj "/CN=$2" -out "$work/$1.csr"
    cat > "$work/$1.ext" <<EOF
basicConstraints = critical, CA:FALSE
keyUsage = critical, digitalSignature
extendedKeyUsage = $3
subjectAltName = $4
subjectKeyIdentifier = hash
authorityKeyIdentifier = keyid
EOF
    openssl x509 -req -in "$work/$1.csr" -CA "$dir/ca.pem" -CAkey "$dir/ca.key" \
        -set_serial "0x$(openssl rand -hex 16)" -days "$days" -sha256 \
        -extfile "$work/$1.ext" -out "$dir/$1.pem" 2>/dev/null
    chmod 600 "$dir/$1.key"
    chmod 644 "$dir/$1.pem"
    echo "$dir/$1.pem: CN=$2, valid $days days"
}

if [ "$new_ca" = yes ] || [ ! -f "$dir/ca.pem" ] || [ ! -f "$dir/ca.key" ]; then
    new_key "$dir/ca.key"
    cat > "$work/ca.cnf" <<EOF
[req]
distinguished_name = dn
x509_extensions = ca
prompt = no
[dn]
CN = Swanky lab CA
[ca]
basicConstraints = critical, CA:TRUE, pathlen:0
keyUsage = critical, keyCertSign, cRLSign
subjectKeyIdentifier = hash
EOF
    openssl req -x509 -new -key "$dir/ca.key" -config "$work/ca.cnf" -sha256 -days 3650 \
        -set_serial "0x$(openssl rand -hex 16)" -out "$dir/ca.pem"
    chmod 600 "$dir/ca.key"
    chmod 644 "$dir/ca.pem"
    echo "$dir/ca.pem: new CA, valid 3650 days"
fi

first=""
alt=""
for name in $routers; do
    [ -n "$first" ] || first=$name
    if is_ip "$name"; then entry="IP:$name"; else entry="DNS:$name"; fi
    alt="${alt:+$alt, }$entry"
done
# serverAuth for clients, clientAuth for a router connecting to another router.
issue router "$first" "serverAuth, clientAuth" "$alt"

for name in "$@"; do
    issue "$name" "$name" "clientAuth" "DNS:$name"
done
