"""Commands a client can send, both ways 3D Slicer sends them, and their replies.

* ``STRING`` on device ``biopsynavCommand``: the first word is the command, the rest is ignored,
  so ``SetRestPose 2``, ``SetRestPose 3``... run it again (Slicer's text node sends a text only
  when it changes). Answered by a ``STRING`` ``biopsynavReply``: ``"<name>: ok: <message>"``
  or ``"<name>: failed: <reason>"``.
* ``COMMAND`` (OpenIGTLink v3, any device name): the command name is the message's name field.
  Answered by an ``RTS_COMMAND`` with the same id and name, whose text is
  ``<Command Name="..." Status="SUCCESS|FAIL" Message="..."/>``.

Commands live in one registry (:func:`register_command`): name -> function of the session that
returns ``(ok, message)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

from .messages import CommandReply
from .protocol import Message, Outgoing, string_message

COMMAND_DEVICE = "biopsynavCommand"
COMMAND_REPLY_DEVICE = "biopsynavReply"

COMMANDS: dict[str, Callable] = {}


def register_command(name: str, run: Callable) -> None:
    """Make ``name`` a command: ``run(session) -> (ok, message)``."""
    COMMANDS[name] = run


register_command("SetRestPose", lambda session: session.set_rest_pose())
register_command("ClearRestPose", lambda session: session.clear_rest_pose())
register_command("GetStatus", lambda session: session.status_summary())


@dataclass(frozen=True)
class Command:
    """A received command: its ``name``, and for a v3 COMMAND its id and device."""

    name: str
    v3: bool = False
    command_id: int = 0
    device: str = ""


def is_command(msg: Message) -> bool:
    """Whether ``msg`` is a command: a STRING on ``biopsynavCommand`` or any COMMAND."""
    return msg.type == "COMMAND" or (msg.type == "STRING" and msg.device == COMMAND_DEVICE)


def parse(msg: Message) -> Command:
    """The command of a command message (:func:`is_command`)."""
    if msg.type == "COMMAND":
        return Command(msg.body.command_name.strip(), True, msg.body.command_id, msg.device)
    words = str(msg.body.string).split()
    return Command(words[0] if words else "")


def run(name: str, session) -> tuple[bool, str]:
    """Run command ``name`` on ``session``; an unknown name fails with the known ones."""
    action = COMMANDS.get(name)
    if action is None:
        return False, f"unknown command {name[:64]!r}; known: {', '.join(COMMANDS)}"
    return action(session)


def reply(command: Command, ok: bool, text: str) -> Outgoing:
    """The answer to ``command``: RTS_COMMAND for a v3 COMMAND, else a STRING."""
    if command.v3:
        body = (f"<Command Name={quoteattr(command.name)} Status="
                f"{quoteattr('SUCCESS' if ok else 'FAIL')} Message={quoteattr(text)}/>")
        msg = CommandReply(command.name, body, command.command_id, device_name=command.device)
        return Outgoing(msg, {"Status": "SUCCESS" if ok else "FAIL"}, min_version=2)
    name = command.name or "(empty command)"
    verdict = f"ok: {text}" if ok else f"failed: {text}"
    return Outgoing(string_message(COMMAND_REPLY_DEVICE, f"{name}: {verdict}"))
