"""A raw AF_PACKET socket that receives from one interface only, from its first frame on.

A packet socket made with a protocol (``socket(AF_PACKET, SOCK_RAW, htons(ETH_P_ALL))``)
receives that protocol from *every* interface of the machine until it is bound, and
keeps what it queued meanwhile: frames of another segment, read later as this
interface's (packet(7): "the socket starts receiving packets of the given protocol
at once, from all interfaces"). Seen here: a test's raw port on its own veth pair
read a reply of the 30-drive demo running beside it (LRW, WKC 90). Made with
protocol 0, a packet socket receives nothing; the protocol comes with ``bind``,
which hooks it to that one interface.
"""

from __future__ import annotations

import socket

ETH_P_ALL = 0x0003  # every protocol (linux/if_ether.h): the only one that sees a card's outgoing frames


def bound_packet_socket(iface: str, protocol: int = ETH_P_ALL) -> socket.socket:
    """A raw packet socket receiving ``protocol`` (host order) on ``iface`` only; OSError (the socket
    closed) when the interface is missing or the process lacks CAP_NET_RAW."""
    sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, 0)
    try:
        sock.bind((iface, protocol))
    except BaseException:
        sock.close()
        raise
    return sock
