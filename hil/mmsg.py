"""The structures of ``sendmmsg(2)`` / ``recvmmsg(2)`` for ctypes (Python's socket module has
neither call): one system call moves a batch of datagrams. Shared by the flooder (flood.py)
and the daemon's stand-in (standin_estopd.py), both run as scripts from this folder."""

from __future__ import annotations

import ctypes

__all__ = ["Iovec", "Mmsghdr", "Msghdr"]


class Iovec(ctypes.Structure):
    _fields_ = [("iov_base", ctypes.c_void_p), ("iov_len", ctypes.c_size_t)]


class Msghdr(ctypes.Structure):
    _fields_ = [("msg_name", ctypes.c_void_p), ("msg_namelen", ctypes.c_uint32),
                ("msg_iov", ctypes.POINTER(Iovec)), ("msg_iovlen", ctypes.c_size_t),
                ("msg_control", ctypes.c_void_p), ("msg_controllen", ctypes.c_size_t),
                ("msg_flags", ctypes.c_int)]


class Mmsghdr(ctypes.Structure):
    _fields_ = [("msg_hdr", Msghdr), ("msg_len", ctypes.c_uint)]
