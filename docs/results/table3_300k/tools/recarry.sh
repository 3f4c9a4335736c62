#!/bin/bash
# stop the mixed B seeds 1-2, carry both, restart them; prints the resume lines
cd /work/science
for p in $(pgrep -f 'memrl.study study.name=mixed_100k'); do kill -TERM $p; done
for i in $(seq 1 30); do pgrep -f 'memrl.study study.name=mixed_100k' >/dev/null || break; sleep 2; done
./carry.sh mixed_100k_v3 B_mixed_s1 /work/main/docs/results/mixed_100k/carry
./carry.sh mixed_100k_v3 B_mixed_s2 /work/main/docs/results/mixed_100k/carry
(SEEDS='[1]' setsid nohup ./mixed.sh '[B]' >> logs/mixed_B1.log 2>&1 < /dev/null &)
sleep 25
(SEEDS='[2]' setsid nohup ./mixed.sh '[B]' >> logs/mixed_B2.log 2>&1 < /dev/null &)
sleep 40
grep -h 'resumed' logs/mixed_B1.log logs/mixed_B2.log | tail -n 2
date
