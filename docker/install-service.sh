#!/bin/sh
# The last build step of both images (docker/Dockerfile, docker/Dockerfile.gpu), run as root in the
# folder holding pyproject.toml, cmc/, service/ and worker/, with the dependencies installed:
#  1. installs the code into the virtual environment and deletes the folder, so that every entry
#     point (uvicorn, celery, python -m, cmc) imports the one installed copy;
#  2. compiles the numba kernels into $CMC_KERNEL_CACHE_SEED, readable by every user; at run time
#     cmc/kernel_cache.py copies them into the writable $NUMBA_CACHE_DIR (the root filesystem is
#     read-only in docker-compose.yml), so no process compiles them again on this CPU model;
#  3. makes the service user (uid 10001, the same in both images: a deployment sharing one
#     artifact volume needs it) and /data, the mount point of each container's working volume
#     (a new volume takes this folder's owner, so the service user can write it).
set -eu
src=$(pwd)
pip install --no-deps "$src"
cd /
rm -rf "$src"
env -u CMC_KERNEL_CACHE_SEED NUMBA_CACHE_DIR="$CMC_KERNEL_CACHE_SEED" \
    python -c "from cmc.kernel_cache import warm_up_kernels; warm_up_kernels()"
chmod -R a+rX "$CMC_KERNEL_CACHE_SEED"
groupadd --gid 10001 cmc
useradd --uid 10001 --gid 10001 --no-log-init --no-create-home --home-dir /tmp cmc
mkdir -p /data
chown cmc:cmc /data
