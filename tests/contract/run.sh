#!/usr/bin/env bash
# The API contract, checked by a property-based fuzzer: Schemathesis (PyPI, in a virtual
# environment made here) with every check and its stateful phase, against a real
# echomap-server process built from this tree, on SQLite and — where PostgreSQL's binaries are
# installed — on a private PostgreSQL server. Exit status 0 only when nothing is found.
#
#   tests/contract/run.sh [EXAMPLES]      # examples per operation, default 200
set -euo pipefail
cd "$(dirname "$0")/../.."
examples="${1:-200}"
work="$(mktemp -d)"
cleanup() {
    kill $(jobs -p) 2> /dev/null || true
    if [ -n "${pg_data:-}" ]; then as_pg "'$pg_bin/pg_ctl' -D '$pg_data' -m immediate stop" > /dev/null 2>&1 || true; fi
    rm -rf "$work"
}
trap cleanup EXIT
venv="${ECHOMAP_CONTRACT_VENV:-target/contract-venv}"
if [ ! -x "$venv/bin/schemathesis" ]; then
    python3 -m venv "$venv"
    "$venv/bin/pip" install -q 'schemathesis>=4.3,<5'
fi
cargo build --release -q -p echomap-server
token="contract-operator-token-0123456789"
printf '%s operator *\n' "$token" > "$work/tokens.txt"

run() { # NAME DATABASE_URL
    local port
    port="$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')"
    target/release/echomap-server --database-url "$2" --token-file "$work/tokens.txt" \
        --listen "127.0.0.1:$port" --rate-limit-per-s 100000 --rate-limit-burst 100000 \
        --rejected-quota-per-day 1000000 > "$work/$1.log" 2>&1 &
    local pid=$!
    for _ in $(seq 100); do curl -sf "http://127.0.0.1:$port/readyz" > /dev/null && break; sleep 0.1; done
    curl -sf -X PUT -H "Authorization: Bearer $token" "http://127.0.0.1:$port/v1/maps/floor1" > /dev/null
    echo "== schemathesis on $1 ($examples examples per operation)"
    local status=0
    "$venv/bin/schemathesis" --no-color --config-file tests/contract/schemathesis.toml run \
        "http://127.0.0.1:$port/openapi.json" -H "Authorization: Bearer $token" \
        --checks all --max-examples "$examples" --seed 1 || status=$?
    kill "$pid"; wait "$pid" 2> /dev/null || true
    return "$status"
}

run sqlite "sqlite://$work/contract.db"
pg_bin="$(dirname "$(ls /usr/lib/postgresql/*/bin/initdb 2> /dev/null | tail -1 || command -v initdb)")"
if [ -x "$pg_bin/initdb" ] && [ -x "$pg_bin/createdb" ]; then
    pg_data="$work/pg"
    pg_port="$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')"
    pg_user=postgres; [ "$(id -u)" -ne 0 ] && pg_user="$(id -un)"
    if [ "$(id -u)" -eq 0 ]; then
        mkdir -p "$pg_data"; chown postgres "$work" "$pg_data"
        as_pg() { su postgres -c "$*"; }
    else
        as_pg() { sh -c "$*"; }
    fi
    as_pg "'$pg_bin/initdb' -D '$pg_data' -U postgres -A trust > /dev/null"
    as_pg "'$pg_bin/pg_ctl' -D '$pg_data' -o '-p $pg_port -k $work -c listen_addresses=127.0.0.1' -l '$work/pg.log' -w start > /dev/null"
    as_pg "'$pg_bin/createdb' -h 127.0.0.1 -p $pg_port -U postgres echomap"
    run postgres "postgres://postgres@127.0.0.1:$pg_port/echomap"
else
    echo "== PostgreSQL binaries not found: the PostgreSQL run is skipped"
fi
