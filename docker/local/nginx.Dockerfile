# Debian's nginx on the local base (docker/local-images.sh): the stand-in for the public nginx image where no
# registry can be reached. Like that image, it renders /etc/nginx/templates/*.template at start
# (nginx-entrypoint.sh: envsubst, NGINX_ENVSUBST_OUTPUT_DIR, NGINX_ENVSUBST_FILTER) and has wget for health checks.
ARG BASE=localhost/gmt-local/python:3.11-bookworm
FROM ${BASE}
RUN printf '#!/bin/sh\nexit 101\n' > /usr/sbin/policy-rc.d && chmod +x /usr/sbin/policy-rc.d \
  && apt-get update && apt-get install -y --no-install-recommends nginx gettext-base wget \
  && rm -rf /var/lib/apt/lists/* && mkdir -p /var/cache/nginx /etc/nginx/templates
COPY nginx-entrypoint.sh /docker-entrypoint.sh
ENTRYPOINT ["/docker-entrypoint.sh"]
STOPSIGNAL SIGQUIT
EXPOSE 80
CMD ["nginx", "-g", "daemon off;"]
