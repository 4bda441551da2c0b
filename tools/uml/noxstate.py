"""Exec a command with ptrace(PTRACE_{GET,SET}REGSET, NT_X86_XSTATE) refused (EIO) by seccomp.

Why: user-mode-linux 6.1/6.12 sizes its copy of a process's extended FPU state (XSAVE area)
for AVX-512 at most, but on a host CPU with AMX the host kernel only accepts a full-size XSAVE
buffer in ``PTRACE_SETREGSET`` and answers ``EFAULT``: UML panics at the first context switch
("userspace - ptrace set fp regs failed, errno = 14"). UML probes for XSAVE support with
``PTRACE_GETREGSET`` at boot and falls back to ``PTRACE_GETFPREGS`` (the 512-byte FXSAVE area) when
the probe fails, so refusing just that request makes it boot. The cost: only the SSE part of the
FPU state is switched between *threads of one guest process* (separate processes keep theirs in
their own host process); the guest runs with glibc's AVX routines disabled to stay clear of that.

    python tools/uml/noxstate.py linux mem=512M ...
"""

from __future__ import annotations

import ctypes
import os
import struct
import sys

PR_SET_NO_NEW_PRIVS = 38
PR_SET_SECCOMP = 22
SECCOMP_MODE_FILTER = 2
AUDIT_ARCH_X86_64 = 0xC000003E
NR_PTRACE = 101
PTRACE_GETREGSET, PTRACE_SETREGSET, NT_X86_XSTATE = 0x4204, 0x4205, 0x202
RET_ALLOW, RET_EIO = 0x7FFF0000, 0x00050000 | 5
LD_ABS_W, JEQ_K, RET_K = 0x20, 0x15, 0x06

# struct seccomp_data: nr @0, arch @4, ip @8, args[i] @16 + 8 i (low word first)
PROGRAM = [
    (LD_ABS_W, 0, 0, 4),
    (JEQ_K, 0, 7, AUDIT_ARCH_X86_64),  # other arch -> allow
    (LD_ABS_W, 0, 0, 0),
    (JEQ_K, 0, 5, NR_PTRACE),  # not ptrace -> allow
    (LD_ABS_W, 0, 0, 32),
    (JEQ_K, 0, 3, NT_X86_XSTATE),  # addr is not NT_X86_XSTATE -> allow
    (LD_ABS_W, 0, 0, 16),
    (JEQ_K, 2, 0, PTRACE_GETREGSET),  # -> EIO
    (JEQ_K, 1, 0, PTRACE_SETREGSET),  # -> EIO
    (RET_K, 0, 0, RET_ALLOW),
    (RET_K, 0, 0, RET_EIO),
]


class _SockFprog(ctypes.Structure):
    _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.c_void_p)]


def install() -> None:
    """Install the filter on this process (inherited by everything it execs and forks)."""
    libc = ctypes.CDLL(None, use_errno=True)
    blob = b"".join(struct.pack("<HBBI", *ins) for ins in PROGRAM)
    buf = ctypes.create_string_buffer(blob, len(blob))
    prog = _SockFprog(len(PROGRAM), ctypes.cast(buf, ctypes.c_void_p))
    if libc.prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_NO_NEW_PRIVS)")
    if libc.prctl(PR_SET_SECCOMP, SECCOMP_MODE_FILTER, ctypes.byref(prog), 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_SECCOMP)")


def main(argv: list[str]) -> int:
    if not argv:
        sys.stderr.write("usage: noxstate.py COMMAND [ARGS...]\n")
        return 2
    install()
    os.execvp(argv[0], argv)
    return 127  # not reached


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
