#!/bin/bash
# usage: ./carry.sh table3_300k_v3 B_constant_s0 /work/main/docs/results/table3_300k/carry
# pack a stopped run (resumable checkpoint included) into DEST/RUN.tar.xz and check the archive byte for byte
set -e
STUDY=$1; RUN=$2; DEST=$3
cd /work/science/studies/$STUDY/runs
mkdir -p "$DEST"
XZ_OPT="-6 -T2" tar --exclude=train.lock -cJf "$DEST/$RUN.tar.xz" "$RUN"
rm -rf /tmp/carrycheck && mkdir /tmp/carrycheck && tar -xJf "$DEST/$RUN.tar.xz" -C /tmp/carrycheck
(cd "$RUN" && find . -type f ! -name train.lock -exec sha256sum {} + | sort -k2) > /tmp/carry_src.sha
(cd /tmp/carrycheck/"$RUN" && find . -type f -exec sha256sum {} + | sort -k2) > /tmp/carry_dst.sha
cmp /tmp/carry_src.sha /tmp/carry_dst.sha && echo "archive equal to the run folder: $(wc -l < /tmp/carry_src.sha) files"
du -sh "$RUN" "$DEST/$RUN.tar.xz"
rm -rf /tmp/carrycheck
