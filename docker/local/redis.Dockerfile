# Debian's redis-server on the local base (docker/local-images.sh): the stand-in for the public redis image
# (redis-server, redis-cli and a shell; data in /data) where no registry can be reached.
ARG BASE=localhost/gmt-local/python:3.11-bookworm
FROM ${BASE}
# policy-rc.d: the package's scripts start no service in the build
RUN printf '#!/bin/sh\nexit 101\n' > /usr/sbin/policy-rc.d && chmod +x /usr/sbin/policy-rc.d \
  && apt-get update && apt-get install -y --no-install-recommends redis-server && rm -rf /var/lib/apt/lists/* \
  && mkdir -p /data
WORKDIR /data
EXPOSE 6379
CMD ["redis-server", "--protected-mode", "no"]
