// Header-version-2 messages (OpenIGTLink v3: extended header and metadata) packed by hand with
// the library's C functions (header byte order, CRC-64): the Debian 1.11 library has no class
// for them. Layout: 58-byte header | 12-byte extended header | content | metadata index | data.
#ifndef BIOPSYNAV_RAW_V2_H
#define BIOPSYNAV_RAW_V2_H

#include <cstring>
#include <string>
#include <utility>
#include <vector>

#include "igtl_header.h"
#include "igtl_util.h"

typedef std::vector<unsigned char> Bytes;

inline void put_be(Bytes& out, unsigned long long v, int n) {
  for (int i = n - 1; i >= 0; --i) out.push_back((unsigned char)((v >> (8 * i)) & 0xff));
}

inline unsigned long long get_be(const unsigned char* p, int n) {
  unsigned long long v = 0;
  for (int i = 0; i < n; ++i) v = (v << 8) | p[i];
  return v;
}

// A whole message: header version 2, `type`, `device`, `content` and string metadata.
inline Bytes pack_v2(const char* type, const char* device, const Bytes& content,
                     const std::vector<std::pair<std::string, std::string> >& meta) {
  Bytes index, data;
  put_be(index, meta.size(), 2);
  for (size_t i = 0; i < meta.size(); ++i) {
    put_be(index, meta[i].first.size(), 2);
    put_be(index, 3, 2);  // US-ASCII
    put_be(index, meta[i].second.size(), 4);
    data.insert(data.end(), meta[i].first.begin(), meta[i].first.end());
    data.insert(data.end(), meta[i].second.begin(), meta[i].second.end());
  }
  Bytes body;
  put_be(body, 12, 2);
  put_be(body, index.size(), 2);
  put_be(body, data.size(), 4);
  put_be(body, 0, 4);  // message id
  body.insert(body.end(), content.begin(), content.end());
  body.insert(body.end(), index.begin(), index.end());
  body.insert(body.end(), data.begin(), data.end());
  igtl_header h;
  std::memset(&h, 0, sizeof(h));
  h.version = 2;
  std::strncpy(h.name, type, IGTL_HEADER_TYPE_SIZE);
  std::strncpy(h.device_name, device, IGTL_HEADER_NAME_SIZE);
  h.timestamp = 0;
  h.body_size = body.size();
  h.crc = crc64(body.data(), body.size(), 0);
  igtl_header_convert_byte_order(&h);
  Bytes msg((unsigned char*)&h, (unsigned char*)&h + IGTL_HEADER_SIZE);
  msg.insert(msg.end(), body.begin(), body.end());
  return msg;
}

#endif
