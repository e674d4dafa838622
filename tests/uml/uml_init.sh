#!/bin/sh
# PID 1 inside User-Mode Linux (started by run_vcan_tests.sh): mount what Python needs, load the CAN
# modules, create vcan0 (CAN FD mtu), run the job the host wrote, store its exit code, power off.
# The job directory comes on the kernel command line as HIL_UML_DIR=... (init gets it as environment).
export PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
DIR=${HIL_UML_DIR:?HIL_UML_DIR not set on the kernel command line}
LOG=$DIR/init.log
{
  mount -t proc proc /proc
  mount -t sysfs sysfs /sys
  [ -d /dev/shm ] && mount -t tmpfs -o size=256m tmpfs /dev/shm   # multiprocessing needs a writable /dev/shm
  ip link set lo up
  M=${HIL_UML_MODULES:-/usr/lib/uml/modules/$(uname -r)}/kernel
  for mod in drivers/net/can/dev/can-dev.ko net/can/can.ko net/can/can-raw.ko drivers/net/can/vcan.ko; do
    insmod "$M/$mod" || echo "insmod $M/$mod failed"
  done
  ip link add dev vcan0 type vcan && ip link set vcan0 mtu 72 && ip link set up vcan0
  ip -details link show vcan0
} > "$LOG" 2>&1
if [ -f "$DIR/env.sh" ]; then . "$DIR/env.sh"; fi
cd "${HIL_UML_CWD:-/}"
sh "$DIR/job.sh" > "$DIR/job.log" 2>&1
echo $? > "$DIR/job.rc"
sync
poweroff -f
