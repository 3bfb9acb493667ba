// 3D Slicer stand-in: an OpenIGTLink client (C++ library) that decodes everything it receives.
//   slicer_client HOST PORT SECONDS [--no-v3]
// Every message is unpacked by the library with its CRC checked: POINT, TRANSFORM, POLYDATA,
// STRING (others are counted and skipped). POINT lists must keep the same names in the same
// order; POLYDATA must be closed triangle meshes with finite points. It sends the commands
// "SetRestPose 1", "SetRestPose 2", "GetStatus 3" as STRING on biopsynavCommand. After SECONDS,
// a second connection sends a v3 COMMAND (header version 2, packed by hand) and reads the
// answer raw: the RTS_COMMAND and the version-2 replies (replies sent before the server read
// the command may be version 1; none after its answer), whose content the library decodes
// once the extended header and metadata are taken off. Prints one JSON object; exits 1 when a
// message failed to decode or a check failed.
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <map>
#include <set>
#include <string>
#include <vector>

#include "igtlClientSocket.h"
#include "igtlMessageHeader.h"
#include "igtlPointMessage.h"
#include "igtlPolyDataMessage.h"
#include "igtlStringMessage.h"
#include "igtlTransformMessage.h"
#include "raw_v2.h"

static double now_s() {
  using namespace std::chrono;
  return duration<double>(steady_clock::now().time_since_epoch()).count();
}

struct Tally {
  std::map<std::string, int> count;  // "TYPE DEVICE"
  std::set<std::string> statuses, replies;
  std::vector<std::string> errors;
  std::vector<std::string> point_names;
  int v2_decoded = 0;
  std::string rts;
};

static void fail(Tally& t, const std::string& what) {
  if (t.errors.size() < 20) t.errors.push_back(what);
  std::fprintf(stderr, "slicer_client: %s\n", what.c_str());
}

// The POLYDATA cell lists walked in the raw (big-endian) body before the library sees it: the
// library trusts the cell sizes and does not stop on a body packed in the wrong byte order.
static bool raw_polydata_ok(const unsigned char* b, unsigned long long size, Tally& t,
                            const std::string& dev) {
  if (size < 40) return fail(t, "POLYDATA shorter than its header: " + dev), false;
  unsigned long long npts = get_be(b, 4), at = 40 + 12 * npts, end = at;
  for (int list = 0; list < 4; ++list) end += get_be(b + 8 + 8 * list, 4);
  if (end > size) return fail(t, "POLYDATA sizes exceed the body: " + dev), false;
  at += get_be(b + 8, 4) + get_be(b + 16, 4);  // vertices and lines come before polygons
  unsigned long long stop = at + get_be(b + 24, 4);
  while (at < stop) {
    unsigned long long n = get_be(b + at, 4);
    if (n != 3 || at + 16 > stop) return fail(t, "POLYDATA cell not a triangle: " + dev), false;
    for (int k = 1; k <= 3; ++k)
      if (get_be(b + at + 4 * k, 4) >= npts)
        return fail(t, "POLYDATA index out of range: " + dev), false;
    at += 16;
  }
  return true;
}

template <class M>
static bool unpack(igtl::Socket* sock, igtl::MessageHeader::Pointer& head, M& msg, Tally& t) {
  msg->SetMessageHeader(head);
  msg->AllocatePack();
  if (sock->Receive(msg->GetPackBodyPointer(), msg->GetPackBodySize()) !=
      msg->GetPackBodySize()) {
    fail(t, std::string("short body of ") + head->GetDeviceType());
    return false;
  }
  if (std::string(head->GetDeviceType()) == "POLYDATA" &&
      !raw_polydata_ok((const unsigned char*)msg->GetPackBodyPointer(),
                       msg->GetPackBodySize(), t, head->GetDeviceName()))
    return false;
  if (!(msg->Unpack(1) & igtl::MessageHeader::UNPACK_BODY)) {
    fail(t, std::string("cannot decode (CRC or content) ") + head->GetDeviceType() + " " +
                head->GetDeviceName());
    return false;
  }
  return true;
}

static void check_point(igtl::PointMessage::Pointer& msg, Tally& t) {
  std::vector<std::string> names;
  for (int i = 0; i < msg->GetNumberOfPointElement(); ++i) {
    igtl::PointElement::Pointer e;
    msg->GetPointElement(i, e);
    float p[3];
    e->GetPosition(p);
    if (!(std::isfinite(p[0]) && std::isfinite(p[1]) && std::isfinite(p[2])))
      fail(t, "POINT with a non-finite position");
    names.push_back(e->GetName());
  }
  if (t.point_names.empty()) t.point_names = names;
  if (names != t.point_names) fail(t, "POINT slots changed name or order");
}

static void check_polydata(igtl::PolyDataMessage::Pointer& msg, Tally& t, const char* dev) {
  igtl::PolyDataPointArray::Pointer pts = msg->GetPoints();
  igtl::PolyDataCellArray::Pointer polys = msg->GetPolygons();
  int n = pts.IsNull() ? 0 : pts->GetNumberOfPoints();
  if (n == 0 || polys.IsNull() || polys->GetNumberOfCells() == 0) {
    fail(t, std::string("empty POLYDATA ") + dev);
    return;
  }
  for (int i = 0; i < n; ++i) {
    float p[3];
    pts->GetPoint(i, p);
    if (!(std::isfinite(p[0]) && std::fabs(p[0]) < 1e4 && std::fabs(p[1]) < 1e4 &&
          std::fabs(p[2]) < 1e4)) {
      fail(t, std::string("POLYDATA point out of range in ") + dev);
      return;
    }
  }
  std::map<std::pair<unsigned, unsigned>, int> edges;
  for (unsigned c = 0; c < polys->GetNumberOfCells(); ++c) {
    if (polys->GetCellSize(c) != 3) {
      fail(t, std::string("POLYDATA cell not a triangle in ") + dev);
      return;
    }
    igtlUint32 v[3];
    polys->GetCell(c, v);
    for (int k = 0; k < 3; ++k) {
      unsigned a = v[k], b = v[(k + 1) % 3];
      if (a >= (unsigned)n || b >= (unsigned)n) {
        fail(t, std::string("POLYDATA index out of range in ") + dev);
        return;
      }
      edges[std::make_pair(a < b ? a : b, a < b ? b : a)]++;
    }
  }
  for (auto& e : edges)
    if (e.second != 2) {
      fail(t, std::string("POLYDATA not closed: ") + dev);
      return;
    }
}

static bool receive_one(igtl::Socket* sock, Tally& t) {
  igtl::MessageHeader::Pointer head = igtl::MessageHeader::New();
  head->InitPack();
  int r = sock->Receive(head->GetPackPointer(), head->GetPackSize());
  if (r != head->GetPackSize()) return false;  // closed or timed out
  head->Unpack();
  std::string type = head->GetDeviceType(), dev = head->GetDeviceName();
  t.count[type + " " + dev]++;
  if (type == "POINT") {
    igtl::PointMessage::Pointer m = igtl::PointMessage::New();
    if (unpack(sock, head, m, t)) check_point(m, t);
  } else if (type == "TRANSFORM") {
    igtl::TransformMessage::Pointer m = igtl::TransformMessage::New();
    unpack(sock, head, m, t);
  } else if (type == "POLYDATA") {
    igtl::PolyDataMessage::Pointer m = igtl::PolyDataMessage::New();
    if (unpack(sock, head, m, t)) check_polydata(m, t, dev.c_str());
  } else if (type == "STRING") {
    igtl::StringMessage::Pointer m = igtl::StringMessage::New();
    if (unpack(sock, head, m, t)) {
      std::string s = m->GetString();
      if (dev == "TrackingStatus") t.statuses.insert(s.substr(0, s.find(':')));
      if (dev == "TrackingStatus" && s.find("tracker connection lost") != std::string::npos)
        t.statuses.insert("no_rest_pose: tracker connection lost");
      if (dev == "biopsynavReply") t.replies.insert(s.substr(0, s.find(':') + 4));
    }
  } else {
    sock->Skip(head->GetBodySizeToRead(), 0);
  }
  return true;
}

static void send_string(igtl::Socket* sock, const char* text) {
  igtl::StringMessage::Pointer m = igtl::StringMessage::New();
  m->SetDeviceName("biopsynavCommand");
  m->SetString(text);
  m->Pack();
  sock->Send(m->GetPackPointer(), m->GetPackSize());
}

// The content of a version-2 body handed to a library class as a version-1 message.
template <class M>
static bool decode_v2_content(const igtl_header& h, const Bytes& body, M msg) {
  unsigned ext = get_be(&body[0], 2), mh = get_be(&body[2], 2), ms = get_be(&body[4], 4);
  if (ext + mh + ms > body.size()) return false;
  Bytes content(body.begin() + ext, body.end() - mh - ms);
  igtl_header v1 = h;
  v1.version = 1;
  v1.body_size = content.size();
  v1.crc = crc64(content.data(), content.size(), 0);
  igtl_header_convert_byte_order(&v1);
  igtl::MessageHeader::Pointer head = igtl::MessageHeader::New();
  head->InitPack();
  std::memcpy(head->GetPackPointer(), &v1, IGTL_HEADER_SIZE);
  head->Unpack();
  msg->SetMessageHeader(head);
  msg->AllocatePack();
  std::memcpy(msg->GetPackBodyPointer(), content.data(), content.size());
  return (msg->Unpack(1) & igtl::MessageHeader::UNPACK_BODY) != 0;
}

static void v3_command(const char* host, int port, Tally& t) {
  igtl::ClientSocket::Pointer sock = igtl::ClientSocket::New();
  if (sock->ConnectToServer(host, port) != 0) return fail(t, "v3 connection refused");
  sock->SetReceiveTimeout(3000);
  std::string text = "<Command Name=\"GetStatus\"/>";
  Bytes content;
  put_be(content, 42, 4);
  const char* name = "GetStatus";
  for (int i = 0; i < 128; ++i) content.push_back(i < 9 ? name[i] : 0);
  put_be(content, 3, 2);
  put_be(content, text.size(), 4);
  content.insert(content.end(), text.begin(), text.end());
  Bytes msg = pack_v2("COMMAND", "SlicerCmd", content,
                      std::vector<std::pair<std::string, std::string> >());
  sock->Send(msg.data(), (int)msg.size());
  for (int i = 0; i < 2000 && (t.rts.empty() || t.v2_decoded < 5); ++i) {
    igtl_header h;
    if (sock->Receive(&h, IGTL_HEADER_SIZE) != IGTL_HEADER_SIZE) break;
    igtl_header_convert_byte_order(&h);
    Bytes body(h.body_size);
    if (h.body_size && sock->Receive(body.data(), (int)h.body_size) != (int)h.body_size) break;
    std::string type(h.name, strnlen(h.name, 12));
    if (crc64(body.data(), body.size(), 0) != h.crc) fail(t, "v2 CRC error in " + type);
    if (h.version != 2) {
      // the server learns the client's version from its first message: what it sent before
      // may be version 1; after the answer to that message (RTS_COMMAND) all must be version 2
      if (!t.rts.empty()) fail(t, "reply to a v2 client in header version 1: " + type);
      continue;
    }
    if (type == "RTS_COMMAND") {
      unsigned ext = get_be(&body[0], 2), mh = get_be(&body[2], 2), ms = get_be(&body[4], 4);
      const unsigned char* c = &body[ext];
      unsigned id = get_be(c, 4), len = get_be(c + 134, 4);
      std::string nm((const char*)c + 4, strnlen((const char*)c + 4, 128));
      std::string txt((const char*)c + 138, len);
      if (ext + 138 + len + mh + ms != body.size()) fail(t, "RTS_COMMAND sizes do not add up");
      char buf[64];
      std::snprintf(buf, sizeof(buf), "%u ", id);
      t.rts = buf + nm + " " + txt;
    } else if (type == "POINT") {
      t.v2_decoded += decode_v2_content(h, body, igtl::PointMessage::New()) ? 1 : 0;
    } else if (type == "TRANSFORM") {
      t.v2_decoded += decode_v2_content(h, body, igtl::TransformMessage::New()) ? 1 : 0;
    }
  }
  sock->CloseSocket();
  if (t.rts.empty()) fail(t, "no RTS_COMMAND answer to the v3 COMMAND");
}

static std::string quoted(const std::string& s) {
  std::string out = "\"";
  for (char c : s) {
    if (c == '"' || c == '\\') out += '\\';
    out += (c >= 0x20 ? c : ' ');
  }
  return out + "\"";
}

int main(int argc, char** argv) {
  if (argc != 4 && argc != 5) {
    std::fprintf(stderr, "usage: slicer_client HOST PORT SECONDS [--no-v3]\n");
    return 2;
  }
  const char* host = argv[1];
  int port = std::atoi(argv[2]);
  double seconds = std::atof(argv[3]);
  igtl::ClientSocket::Pointer sock = igtl::ClientSocket::New();
  if (sock->ConnectToServer(host, port) != 0) {
    std::fprintf(stderr, "slicer_client: cannot connect to %s:%d\n", host, port);
    return 1;
  }
  sock->SetReceiveTimeout(3000);
  Tally t;
  const char* commands[] = {"SetRestPose 1", "SetRestPose 2", "GetStatus 3"};
  int sent_commands = argc == 4 ? 0 : 3;
  double start = now_s();
  while (now_s() - start < seconds) {
    if (sent_commands < 3 && now_s() - start > 0.3 * (sent_commands + 1))
      send_string(sock, commands[sent_commands++]);
    if (!receive_one(sock, t)) {
      fail(t, "connection closed or silent for 3 s");
      break;
    }
  }
  sock->CloseSocket();
  if (argc == 4) v3_command(host, port, t);
  std::printf("{\"counts\": {");
  bool first = true;
  for (auto& c : t.count) {
    std::printf("%s%s: %d", first ? "" : ", ", quoted(c.first).c_str(), c.second);
    first = false;
  }
  std::printf("}, \"statuses\": [");
  first = true;
  for (auto& s : t.statuses) std::printf("%s%s", first ? "" : ", ", quoted(s).c_str()), first = false;
  std::printf("], \"replies\": [");
  first = true;
  for (auto& s : t.replies) std::printf("%s%s", first ? "" : ", ", quoted(s).c_str()), first = false;
  std::printf("], \"point_names\": [");
  first = true;
  for (auto& s : t.point_names) std::printf("%s%s", first ? "" : ", ", quoted(s).c_str()), first = false;
  std::printf("], \"rts\": %s, \"v2_decoded\": %d, \"errors\": [", quoted(t.rts).c_str(),
              t.v2_decoded);
  first = true;
  for (auto& s : t.errors) std::printf("%s%s", first ? "" : ", ", quoted(s).c_str()), first = false;
  std::printf("]}\n");
  return t.errors.empty() ? 0 : 1;
}
