#!/bin/sh
# PID 1 inside user-mode-linux: mount the basics, load the CAN modules, bring up vcan0 (CAN FD
# capable: mtu 72), run $TEST with its output in $RES/out.txt and its exit code in $RES/rc.txt,
# then halt. KEY=VALUE words on the kernel command line arrive here as environment variables
# (MODDIR: where the kernel's modules are, when UML is not the system package).
export PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin HOME=/root
mount -t proc proc /proc
mount -t sysfs sys /sys
mkdir -p /dev/pts /dev/shm
mount -t devpts devpts /dev/pts
mount -t tmpfs shm /dev/shm
M=${MODDIR:-/usr/lib/uml/modules/$(uname -r)}/kernel
for k in net/can/can.ko net/can/can-raw.ko drivers/net/can/dev/can-dev.ko drivers/net/can/vcan.ko; do
    insmod "$M/$k" 2>>"$RES/init.txt"
done
ip link set lo up
ip link add dev vcan0 type vcan && ip link set vcan0 mtu 72 && ip link set up vcan0
ip -details link show vcan0 >>"$RES/init.txt" 2>&1
export HIL_IN_UML=1
sh "$TEST" >"$RES/out.txt" 2>&1
echo $? >"$RES/rc.txt"
sync
halt -f
