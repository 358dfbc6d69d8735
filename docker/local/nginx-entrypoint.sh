#!/bin/sh
# What the public nginx image does at start, for the templates: each /etc/nginx/templates/NAME.template is
# rendered to $NGINX_ENVSUBST_OUTPUT_DIR/NAME (default /etc/nginx/conf.d), substituting only the environment
# variables whose names match $NGINX_ENVSUBST_FILTER (nginx's own $variables are left alone). Then runs the command.
set -eu
out=${NGINX_ENVSUBST_OUTPUT_DIR:-/etc/nginx/conf.d}
names=$(env | cut -d= -f1 | grep -E -- "${NGINX_ENVSUBST_FILTER:-.}" || true)
defined=$(for n in $names; do printf '${%s} ' "$n"; done)
for t in /etc/nginx/templates/*.template; do
  [ -f "$t" ] || continue
  envsubst "$defined" < "$t" > "$out/$(basename "$t" .template)"
done
exec "$@"
